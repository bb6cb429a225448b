"""`calibrate_from_subject`: pairs -> offsets -> chained poses -> bundle adjustment -> anchors and scale."""

from __future__ import annotations

import copy
import logging
import math
from typing import NoReturn

import numpy as np
from tqdm import tqdm

from sfm.subject.bundle import Bundle, adjust, camera_residuals, held_out_px, residuals_px, rotation, supported
from sfm.subject.chain import Knots, initial_poses, make_knots
from sfm.subject.focals import RANGE, division_to_opencv, estimate_distortion, self_calibrate
from sfm.subject.model import (
    CLAIM_RATIO,
    INLIER_PX,
    MIN_DISTINCT,
    MIN_INLIERS,
    MIN_SHARED,
    NEVER_OVERLAP,
    NO_USABLE_PAIR,
    SEED,
    UNTESTED,
    Lens,
    PairResult,
    ScalePointsError,
    SubjectCalibrationError,
    SubjectCamera,
    SubjectOptions,
    SubjectResult,
    SubjectVideo,
    max_residual_px,
    reasons_text,
)
from sfm.subject.observations import VideoObs, build_observations, normalize
from sfm.subject.offsets import components, solve_offsets
from sfm.subject.pairs import DISTINCT, PairFit, fit_at, fit_pair, search_range
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

PP_SIGMA = 0.0  # principal point prior around the image centre (fraction of the long side); 0 = held there
BOUND_TOLERANCE = 0.01  # a self-calibrated focal within this (log) of the search's bound sits at it
HELD_OUT_GAIN = 0.95  # radial distortion is kept where it predicts held-out observations this much better
BLOCK_S = 0.5  # seconds of a camera's own time per held-out block
FOCAL_SIGMA = 0.1  # relative prior on the self-calibrated focal (weighted like all of a camera's observations)
# the same prior loosened: kept where the focals it lets the bundle move predict held-out observations HELD_OUT_GAIN
# better (self-calibration can be 10 % off where the bundle itself fixes the focal)
LOOSE_FOCAL_SIGMA = 0.5


def calibrate_from_subject(
    tracks: Tracks, videos: list[SubjectVideo], options: SubjectOptions | None = None
) -> SubjectResult:
    """Pose static cameras (and their clock offsets, and unknown focals) from the 2D tracks of a moving subject,
    at the noise scale `options.inlier_px` (INLIER_PX when None; `choose_noise` tries several)."""
    options = options or SubjectOptions()
    inlier_px = INLIER_PX if options.inlier_px is None else options.inlier_px
    rng = np.random.default_rng(SEED)
    tracks = tracks.canonical()
    points, obs = build_observations(tracks, videos)
    _check_scale_points(points, options)
    with_tracks = [i for i, o in enumerate(obs) if o.count() > 0]
    failed: dict[str, str] = {o.name: "no tracks" for o in obs if o.count() == 0}
    if len(with_tracks) < 2:
        raise SubjectCalibrationError(f"{len(with_tracks)} video(s) have tracks; track the subject in at least two")

    fits = _fit_pairs(obs, with_tracks, options, rng, inlier_px)
    pairs = [_pair_result(obs, f) for f in fits]
    usable = [f for f in fits if f.usable]
    if not usable:
        _no_usable_pair(fits, options)

    anchors = [i for i in with_tracks if videos[i].cam_from_world is not None]
    groups = components(len(obs), [(f.a, f.b) for f in usable])
    reference = anchors[0] if anchors else _largest_group_first(groups, usable, with_tracks)
    offsets, kept = _chain_offsets(obs, usable, reference)
    for i in with_tracks:
        if not np.isfinite(offsets[i]):
            failed[obs[i].name] = _why(obs, fits, i, groups, reference)

    kept_fits = _refit_to_offsets(obs, usable, kept, offsets, inlier_px)
    if not kept_fits:
        raise SubjectCalibrationError("no pair's epipolar geometry agrees with the chained time offsets")
    lens, obs, bundle, lens_check = _choose_lens(
        obs, kept_fits, offsets, len(points), reference, failed, options, inlier_px
    )
    metric, fixed_anchor = _fix_frame(bundle, obs, videos, inlier_px)
    bundle.knots.X[~supported(bundle, obs)] = np.nan  # knots no two cameras see are extrapolations
    if options.scale is not None and not metric:
        _apply_scale(bundle, points, options.scale, fixed_anchor)
        metric = True
    return SubjectResult(
        cameras=_cameras(bundle, obs),
        pairs=pairs,
        failed=failed,
        metric=metric,
        points={p: bundle.knots.X[:, i].copy() for i, p in enumerate(points)},
        times=bundle.knots.times,
        lens=lens,
        lens_check=lens_check,
        inlier_px=inlier_px,
        focal_sigma=bundle.focal_sigma if bundle.focal_sigma != FOCAL_SIGMA else None,
    )


def _adjusted(
    obs: list[VideoObs],
    fits: list[PairFit],
    offsets: np.ndarray,
    n_points: int,
    reference: int,
    failed: dict[str, str],
    inlier_px: float,
) -> Bundle:
    """Chained poses and the bundle adjustment, once `_estimate_focals` has set the unknown-K cameras' intrinsics
    (`obs` and `failed` are updated)."""
    knots = make_knots(obs, offsets, n_points)
    poses = initial_poses(obs, offsets, fits, knots, inlier_px, failed)
    bundle = _initial_bundle(obs, poses, offsets, knots, reference)
    adjust(bundle, obs, inlier_px)
    _refuse_unsupported(bundle, obs, failed, inlier_px)
    return bundle


def _choose_lens(
    obs: list[VideoObs],
    fits: list[PairFit],
    offsets: np.ndarray,
    n_points: int,
    reference: int,
    failed: dict[str, str],
    options: SubjectOptions,
    inlier_px: float,
) -> tuple[Lens, list[VideoObs], Bundle, dict[str, float]]:
    """The bundle with the lens model of `options` or, with AUTO and unknown intrinsics, the simpler model
    (FOCAL) unless radial distortion predicts held-out observations better by HELD_OUT_GAIN. Returns the model,
    the observations and bundle it was solved with, and the held-out errors compared."""
    unknown = any(not o.known_K for o in obs)
    if options.lens is not Lens.AUTO or not unknown:
        fixed = options.lens if unknown and options.lens is not Lens.AUTO else Lens.FOCAL
        _estimate_focals(obs, fits, fixed is Lens.RADIAL, options.focals)
        bundle = _adjusted(obs, fits, offsets, n_points, reference, failed, inlier_px)
        if options.focal_sigma is not None and unknown:
            bundle.focal_sigma = options.focal_sigma
            adjust(bundle, obs, inlier_px, rounds=1)
        return fixed, obs, bundle, {}
    tried: dict[Lens, tuple[list[VideoObs], Bundle, dict[str, str]]] = {}
    error: SubjectCalibrationError | None = None
    for lens in (Lens.FOCAL, Lens.RADIAL):
        mine, mine_fits, mine_failed = copy.deepcopy(obs), copy.deepcopy(fits), dict(failed)
        try:
            radial = _estimate_focals(mine, mine_fits, lens is Lens.RADIAL)
            if lens is Lens.RADIAL and not radial:
                break  # no distortion found: the same model as FOCAL, whose bundle is not solved again
            bundle = _adjusted(mine, mine_fits, offsets, n_points, reference, mine_failed, inlier_px)
        except SubjectCalibrationError as e:
            error = error or e
            continue
        tried[lens] = (mine, bundle, mine_failed)
    if not tried:
        assert error is not None
        raise error
    check: dict[str, float] = {}
    chosen = Lens.FOCAL if Lens.FOCAL in tried else Lens.RADIAL
    if len(tried) == 2:  # the same observations left out of both
        for lens, (mine, bundle, _) in tried.items():
            test = [_thinned(mine[c]) for c in bundle.cams]
            check[lens.value] = held_out_px(bundle, mine, inlier_px, BLOCK_S, test)
        simple, rich = tried[Lens.FOCAL][1], tried[Lens.RADIAL][1]
        if len(rich.cams) >= len(simple.cams) and check["radial"] < HELD_OUT_GAIN * check["focal"]:
            chosen = Lens.RADIAL
    log.info(
        "lens model: %s (held-out median reprojection error: %s)",
        chosen.value,
        ", ".join(f"{k} {v:.3f} px" for k, v in check.items()) or "one model tried",
    )
    mine, bundle, mine_failed = tried[chosen]
    if options.focal_sigma is None:
        mine, bundle = _loosened_focal(mine, bundle, inlier_px, check, check.get(chosen.value))
    failed.clear()
    failed.update(mine_failed)
    return chosen, mine, bundle, check


def _loosened_focal(
    obs: list[VideoObs], bundle: Bundle, inlier_px: float, check: dict[str, float], held: float | None = None
) -> tuple[list[VideoObs], Bundle]:
    """The bundle adjusted again with the focal prior loosened to LOOSE_FOCAL_SIGMA, where its focals predict
    held-out observations HELD_OUT_GAIN better than the self-calibrated prior's (`check` gets both errors; `held`:
    the bundle's own held-out error, where the lens choice measured it already)."""
    loose_obs, loose = copy.deepcopy(obs), copy.deepcopy(bundle)
    loose.focal_sigma = LOOSE_FOCAL_SIGMA
    try:
        adjust(loose, loose_obs, inlier_px, rounds=1)
    except SubjectCalibrationError:
        return obs, bundle
    test = [_thinned(obs[c]) for c in bundle.cams]
    if held is None:
        held = held_out_px(bundle, obs, inlier_px, BLOCK_S, test)
    free = held_out_px(loose, loose_obs, inlier_px, BLOCK_S, test)
    check["focal_prior"], check["focal_loose"] = held, free
    log.info("focal prior: held-out %.3f px, loosened %.3f px (focals %s)", held, free, np.round(loose.focal))
    if free < HELD_OUT_GAIN * held:
        return loose_obs, loose
    return obs, bundle


def _check_scale_points(points: list[str], options: SubjectOptions) -> None:
    if options.scale is not None:
        missing = [p for p in options.scale[:2] if p not in points]
        if missing:
            raise SubjectCalibrationError(
                f"scale point(s) {', '.join(missing)} are not in the tracks (points: "
                f"{', '.join(points[:10])}); fix --scale (options.scale)"
            )


def _fit_pairs(
    obs: list[VideoObs], with_tracks: list[int], options: SubjectOptions, rng: np.random.Generator, inlier_px: float
) -> list[PairFit]:
    """Every pair of tracked videos: its time offset (searched, or at the known offsets) and epipolar geometry."""
    fits: list[PairFit] = []
    known, claimed = options.offsets or {}, options.claimed_offsets or {}
    pairs = [(a, b) for n, a in enumerate(with_tracks) for b in with_tracks[n + 1 :]]
    for a, b in tqdm(pairs, desc="subject path: pairs' offsets and geometry", unit="pair", leave=False):
        if obs[a].name in known and obs[b].name in known:  # own_b = own_a + shift at one instant
            fit = fit_at(obs[a], obs[b], a, b, known[obs[a].name] - known[obs[b].name], inlier_px)
        else:
            fit = fit_pair(obs[a], obs[b], a, b, options.max_offset, rng, inlier_px)
            if obs[a].name in claimed and obs[b].name in claimed:
                shift = claimed[obs[a].name] - claimed[obs[b].name]
                fit = _tested_claim(obs, fit, shift, inlier_px, options.max_offset)
        log.info("pair %s-%s: %s", obs[a].name, obs[b].name, _pair_words(fit))
        fits.append(fit)
    return fits


def _pair_words(fit: PairFit) -> str:
    """One pair's fit for the log: offset, inliers, and the runner-up ratio and degeneracy only where they apply."""
    words = [f"offset {-fit.shift:.3f} s", f"{fit.inliers}/{fit.shared} inliers"]
    if math.isfinite(fit.runner_up_ratio):
        words.append(f"runner-up ratio {fit.runner_up_ratio:.2f}")
    if fit.degenerate:
        words.append(f"degenerate: {fit.degenerate}")
    if fit.reason:
        words.append(fit.reason)
    return ", ".join(words)


def _tested_claim(obs: list[VideoObs], searched: PairFit, shift: float, inlier_px: float, max_offset: float) -> PairFit:
    """The pair at its declared shift, unless its tracks contradict it: the searched shift lies over a frame away,
    not at the end of the search range (`max_offset`: a best score there is the range's, not the tracks' minimum),
    and scores CLAIM_RATIO better (then the searched fit, ambiguous or not, its `claim` saying why), or the
    declared shift gives no usable geometry where the searched one does. Elsewhere the declaration decides the
    pair's offset (a triggered rig's clocks agree to far under a frame)."""
    a, b = searched.a, searched.b
    period = max(obs[a].period, obs[b].period)
    declared = fit_at(obs[a], obs[b], a, b, shift, inlier_px)
    lo, hi = search_range(obs[a], obs[b], max_offset)
    inside = lo + period < searched.shift < hi - period  # a best score at the range's end is the range's
    apart = abs(searched.shift - shift) > period and inside
    if apart and searched.E is not None and searched.score > CLAIM_RATIO * declared.score:
        searched.claim = (
            f"contradicted: the tracks put the offset at {-searched.shift + 0.0:.3f} s, not {-shift + 0.0:.3f} s "
            f"(score {searched.score / max(declared.score, 1e-9):.2f} x the declared one's)"
        )
        log.warning("pair %s-%s: the declared clocks are %s", obs[a].name, obs[b].name, searched.claim)
        return searched
    if not declared.usable and searched.usable:
        searched.claim = f"not used: at the declared offset, {declared.reason or declared.degenerate}"
        return searched
    # a pair without geometry at any offset (no shared observations) neither holds nor contradicts the claim
    declared.claim = "held" if declared.usable else UNTESTED
    declared.runner_up_ratio = searched.runner_up_ratio  # the search's: how clearly the tracks alone fix it
    return declared


def _pair_result(obs: list[VideoObs], f: PairFit) -> PairResult:
    return PairResult(
        a=obs[f.a].name,
        b=obs[f.b].name,
        offset=-f.shift,
        inliers=f.inliers,
        shared=f.shared,
        runner_up_ratio=f.runner_up_ratio,
        degenerate=f.degenerate,
        ambiguous=f.ambiguous,
        distinct=f.distinct,
        reason=f.reason,
        claim=f.claim,
    )


def _no_usable_pair(fits: list[PairFit], options: SubjectOptions) -> NoReturn:
    degenerate = sorted({f.degenerate for f in fits if f.degenerate})
    if degenerate:
        raise SubjectCalibrationError(
            f"degenerate motion in every pair ({'; '.join(degenerate)}): the tracks cannot fix an epipolar "
            "geometry; record a subject moving in all three dimensions across the views, or track more points"
        )
    most = max(f.shared for f in fits)
    raise SubjectCalibrationError(
        f"no pair of videos shares {MIN_SHARED} observations at any time offset "
        f"within ±{options.max_offset:g} s (best {most}); record longer overlapping motion or track more points, "
        "or give --max-offset where the cameras were started further apart"
    )


def _chain_offsets(obs: list[VideoObs], usable: list[PairFit], reference: int) -> tuple[np.ndarray, list[int]]:
    """Every video's clock offset from the pairs' offsets, `reference` at 0; returns the offsets (NaN where no
    pair reaches) and the indices of the pairs kept."""
    period = max(o.period for o in obs)
    # an ambiguous pair barely counts: it decides an offset only where no trusted pair reaches
    edges = [(f.a, f.b, -f.shift, float(f.inliers) * (1e-3 if f.ambiguous else 1.0)) for f in usable]
    offsets, kept = solve_offsets(len(obs), edges, {reference: 0.0}, tolerance=1.5 * period)
    if not np.isfinite(offsets[reference]) or len(kept) == 0:
        raise SubjectCalibrationError("no usable pair includes the reference video; check the tracks overlap in time")
    return offsets, kept


def _initial_bundle(
    obs: list[VideoObs],
    poses: dict[int, tuple[np.ndarray, np.ndarray]],
    offsets: np.ndarray,
    knots: Knots,
    reference: int,
) -> Bundle:
    """The chained poses as a bundle; the camera at the origin is held, the farthest one fixes the scale."""
    cams = sorted(poses)
    first = next(j for j, c in enumerate(cams) if np.allclose(poses[c][1], 0) and np.allclose(poses[c][0], np.eye(3)))
    bundle = Bundle(
        cams=cams,
        rvec=np.array([rotation_vector(poses[c][0]) for c in cams]),
        t=np.array([poses[c][1] for c in cams]),
        focal=np.array([obs[c].focal for c in cams]),
        k1=np.array([_dist(obs[c])[0] for c in cams]),
        k2=np.array([_dist(obs[c])[1] for c in cams]),
        pp=np.array([obs[c].K[:2, 2] for c in cams]),
        offsets=offsets.copy(),
        knots=knots,
        fixed_pose={first},
        fixed_offset={reference},
        gauge=None,
        keep=[_thinned(obs[c]) for c in cams],
    )
    second = max((j for j in range(len(cams)) if j != first), key=lambda j: np.linalg.norm(bundle.t[j]))
    bundle.gauge = (first, second, float(np.linalg.norm(bundle.t[second])))
    finite = np.isfinite(knots.X[..., 0])
    bundle.depth = float(np.median(np.linalg.norm(knots.X[finite], axis=-1))) if finite.any() else 1.0
    bundle.focal_prior = bundle.focal.copy()
    if PP_SIGMA > 0:
        bundle.pp_prior = np.array([obs[c].video_centre for c in cams])
        bundle.pp_sigma = PP_SIGMA * max(max(obs[c].video.width, obs[c].video.height) for c in cams)
    bundle.focal_sigma = FOCAL_SIGMA
    return bundle


def _dist(o: VideoObs) -> np.ndarray:
    return np.zeros(5) if o.known_K or o.dist is None else o.dist


def _refuse_unsupported(bundle: Bundle, obs: list[VideoObs], failed: dict[str, str], inlier_px: float) -> None:
    """Drop the cameras the adjusted data do not support, and adjust the others again."""
    refused = _refuse(bundle, obs, failed, inlier_px)
    if refused:
        _drop(bundle, refused)
        if len(bundle.cams) < 2:
            # every camera's reason, the ones left out before the adjustment too (two groups, no usable pair)
            raise SubjectCalibrationError(
                "the bundle adjustment cannot support the cameras' poses: "
                + reasons_text({name: why for name, why in failed.items() if why != "no tracks"})
            )
        adjust(bundle, obs, inlier_px, rounds=1)


def _fix_frame(
    bundle: Bundle, obs: list[VideoObs], videos: list[SubjectVideo], inlier_px: float
) -> tuple[bool, list[int]]:
    """Move the solution onto the anchors' frame (and scale, with two or more) and adjust once more.

    Returns whether the scale is metric and the anchors' positions in `bundle.cams`."""
    cams = bundle.cams
    metric = False
    fixed_anchor = [j for j, c in enumerate(cams) if videos[c].cam_from_world is not None]
    if fixed_anchor:
        _align_to_anchors(bundle, videos, fixed_anchor)
        bundle.fixed_pose = set(fixed_anchor)
        if len(fixed_anchor) >= 2:
            bundle.gauge = None
            metric = True
        else:
            j = fixed_anchor[0]
            other = max(
                (i for i in range(len(cams)) if i != j),
                key=lambda i: np.linalg.norm(_centre(bundle, i) - _centre(bundle, j)),
            )
            bundle.gauge = (j, other, float(np.linalg.norm(_centre(bundle, other) - _centre(bundle, j))))
        adjust(bundle, obs, inlier_px, rounds=1)
    return metric, fixed_anchor


def _cameras(bundle: Bundle, obs: list[VideoObs]) -> list[SubjectCamera]:
    res = residuals_px(bundle, obs)
    cameras = []
    for j, c in enumerate(bundle.cams):
        K = obs[c].K.copy()
        dist = obs[c].dist if obs[c].known_K else np.array([bundle.k1[j], bundle.k2[j], 0.0, 0.0, 0.0])
        cameras.append(
            SubjectCamera(
                name=obs[c].name,
                K=K,
                dist=dist,
                R=rotation(bundle.rvec[j]),
                t=bundle.t[j].copy(),
                offset=float(bundle.offsets[c]),
                inliers=len(res[j]),
                # observations of knots left unsupported (NaN) have no residual
                residual_px=float(np.nanmedian(res[j])) if np.isfinite(res[j]).any() else float("nan"),
            )
        )
    return cameras


def rotation_vector(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def _thinned(o: VideoObs, budget: int = 2500) -> np.ndarray:
    """(F, P) observations used by the bundle: every k-th frame so that a camera has about `budget` (speed)."""
    seen = np.isfinite(o.xy[..., 0])
    stride = max(1, int(np.ceil(seen.sum() / budget)))
    seen[np.arange(len(seen)) % stride != 0] = False
    return seen


def _refuse(b: Bundle, obs: list[VideoObs], failed: dict[str, str], inlier_px: float) -> list[int]:
    """Positions in `b.cams` whose adjusted pose is not supported: large residuals or too few agreeing points."""
    limit = max_residual_px(inlier_px)
    out = []
    for j, (res, f, p) in enumerate(camera_residuals(b, obs)):
        o = obs[b.cams[j]]
        good = res <= 3 * inlier_px
        median = float(np.median(res)) if len(res) else float("inf")
        cells = np.floor(o.xy[f[good], p[good]] / (DISTINCT * max(o.video.width, o.video.height)))  # (M, 2)
        distinct = len(np.unique(cells, axis=0)) if len(cells) else 0
        if not len(res):
            # the adjustment's outlier rounds left none of its observations (or it had none at the others' times)
            why = (
                f"none of its observations lies within {3 * inlier_px:g} px of the trajectory the bundle adjustment "
                "fits to all cameras (a pose or a point correspondence the tracks do not support)"
            )
        elif median > limit:
            why = f"median reprojection error {median:.1f} px after the bundle adjustment (> {limit:g})"
        elif int(good.sum()) < MIN_INLIERS:
            why = f"only {int(good.sum())} observations agree with the others' trajectory (< {MIN_INLIERS})"
        elif distinct < MIN_DISTINCT // 2:
            why = f"its agreeing observations cover only {distinct} distinct image positions"
        else:
            continue
        log.warning("camera %s refused: %s", o.name, why)
        failed[o.name] = why
        out.append(j)
    return out


def _drop(b: Bundle, positions: list[int]) -> None:
    """Remove cameras from the bundle; the gauge moves to the remaining ones."""
    keep = [j for j in range(len(b.cams)) if j not in positions]
    fixed = [keep.index(j) for j in sorted(b.fixed_pose) if j in keep]
    b.cams = [b.cams[j] for j in keep]
    b.rvec, b.t, b.focal = b.rvec[keep], b.t[keep], b.focal[keep]
    b.k1, b.k2, b.pp = b.k1[keep], b.k2[keep], b.pp[keep]
    if b.focal_prior is not None:
        b.focal_prior = b.focal_prior[keep]
    if b.pp_prior is not None:
        b.pp_prior = b.pp_prior[keep]
    b.keep = [b.keep[j] for j in keep]
    if len(keep) < 2:
        return
    b.fixed_pose = set(fixed) or {0}
    first = min(b.fixed_pose)
    second = max(
        (j for j in range(len(keep)) if j != first), key=lambda j: np.linalg.norm(_centre(b, j) - _centre(b, first))
    )
    b.gauge = (
        None
        if len(b.fixed_pose) >= 2
        else (first, second, float(np.linalg.norm(_centre(b, second) - _centre(b, first))))
    )


def _centre(b: Bundle, j: int) -> np.ndarray:
    return -rotation(b.rvec[j]).T @ b.t[j]


def _largest_group_first(groups: list[set[int]], usable: list[PairFit], with_tracks: list[int]) -> int:
    """The reference video without anchors: the first tracked video of the largest group that usable pairs connect
    (most inliers on a tie), so that two groups of cameras sharing no point pose the larger one."""

    def size(group: set[int]) -> tuple[int, int]:
        return len(group), sum(f.inliers for f in usable if f.a in group)

    best = max((g for g in groups if g & set(with_tracks)), key=size)
    return next(i for i in with_tracks if i in best)


def _why(obs: list[VideoObs], fits: list[PairFit], i: int, groups: list[set[int]], reference: int) -> str:
    mine = [f for f in fits if i in (f.a, f.b)]
    group = next(g for g in groups if i in g)
    if len(group) > 1 and reference not in group:
        posed = next(g for g in groups if reference in g)
        across = {f.reason or f.degenerate or "" for f in fits if {f.a, f.b} & group and {f.a, f.b} & posed}
        said = "; ".join(sorted(r for r in across if r)) or "none fitted"
        return (
            f"{NO_USABLE_PAIR} joins its group of videos ({', '.join(sorted(obs[j].name for j in group))}) to the "
            f"group the path poses ({', '.join(sorted(obs[j].name for j in posed))}; their pairs: {said}): track "
            "points that both groups see at one time, or register each group on its own"
        )
    if all(f.shared < 8 or (f.reason or "").startswith(("the videos never", "at most")) for f in mine):
        return f"{NEVER_OVERLAP} (within max_offset)"
    # the pairs that share observations say why; the others only that they share none
    sharing = [f for f in mine if f.shared >= 8 and not (f.reason or "").startswith(("the videos never", "at most"))]
    reasons = [
        f"with {obs[f.b if f.a == i else f.a].name}: "
        + (_DEGENERATE.get(f.degenerate, f.degenerate) if f.degenerate else f.reason or "inconsistent offset")
        for f in sharing
    ]
    return f"{NO_USABLE_PAIR}: " + "; ".join(reasons)


# What a degenerate pair's word means, in its refusal (at a wrong offset the few agreeing positions often lie so)
_DEGENERATE = {
    "line": "line (the agreeing positions lie near one line in a view, at the best offset searched)",
    "plane": "plane (the agreeing positions lie on one plane, at the best offset searched)",
}


def _refit_to_offsets(
    obs: list[VideoObs], usable: list[PairFit], kept: list[int], offsets: np.ndarray, inlier_px: float
) -> list[PairFit]:
    """The pairs at the chained offsets: a pair whose own offset disagrees (dropped or ambiguous) is refitted there."""
    out = []
    for k, f in enumerate(usable):
        if not (np.isfinite(offsets[f.a]) and np.isfinite(offsets[f.b])):
            continue
        shift = -float(offsets[f.b] - offsets[f.a])
        tol = 0.5 * max(obs[f.a].period, obs[f.b].period)
        if k in kept and abs(shift - f.shift) <= tol:
            out.append(f)
            continue
        g = fit_at(obs[f.a], obs[f.b], f.a, f.b, shift, inlier_px)
        log.info(
            "pair %s-%s refitted at the chained offset %.3f s (own %.3f s): %d inliers, %s",
            obs[f.a].name,
            obs[f.b].name,
            -shift,
            -f.shift,
            g.inliers,
            g.reason or g.degenerate or "usable",
        )
        if g.usable:
            out.append(g)
    return out


def _estimate_focals(
    obs: list[VideoObs], fits: list[PairFit], radial: bool, given: dict[str, float] | None = None
) -> bool:
    """Unknown K: focals that make every pair's fundamental matrix most essential (self-calibration), after the
    radial distortion (when `radial`) that makes the pairs' epipolar geometry fit best; `given` (per video name)
    replaces the self-calibrated focal. Returns whether any distortion was found."""
    unknown = [i for i, o in enumerate(obs) if not o.known_K]
    if not unknown:
        return False
    lam = estimate_distortion(obs, fits) if radial else {}
    focals = self_calibrate(obs, fits)
    _refuse_bounded(obs, {i: f for i, f in focals.items() if obs[i].name not in (given or {})})
    for i in unknown:
        new = (given or {}).get(obs[i].name, focals.get(i))
        if new is None:
            continue
        o = obs[i]
        old = o.focal
        half = 0.5 * max(o.video.width, o.video.height)
        if lam.get(i, 0.0) != 0.0:
            o.dist = division_to_opencv(lam[i], new, half, o.video.width, o.video.height)
        log.info("camera %s: focal %.0f px, distortion %s from self-calibration", o.name, new, o.dist)
        for f in fits:  # the pixels (centred on the principal point) normalized again with the new focal and lens
            if f.a == i:
                f.xa = _renormalized(f.xa * old, o, new)
            if f.b == i:
                f.xb = _renormalized(f.xb * old, o, new)
        o.set_focal(new)
    return any(v != 0.0 for v in lam.values())


def _refuse_bounded(obs: list[VideoObs], focals: dict[int, float]) -> None:
    """Self-calibrated focals at the search's bounds (RANGE x the long side) are no measurement: the pairs'
    geometry does not determine them (blob tracks of a mouse in a lab's arena gave 0.25 and 4 x, then the path ran
    for minutes on those lenses), or the lens lies outside the range (a telephoto): refused, naming them."""
    at = []
    for i, focal in focals.items():
        ratio = focal / max(obs[i].video.width, obs[i].video.height)
        if min(abs(np.log(ratio / bound)) for bound in RANGE) < BOUND_TOLERANCE:
            at.append(f"{obs[i].name} ({focal:.0f} px, {ratio:.2g} x its image's long side)")
    if at:
        raise SubjectCalibrationError(
            f"the tracks do not determine the focal length of {', '.join(at)}: self-calibration stopped at the "
            f"bound of its range ({RANGE[0]:g}-{RANGE[1]:g} x the long side); give the cameras' intrinsics "
            "(--intrinsics, or --board with a calibration board's corners), or track points spread in depth"
        )


def _renormalized(centred: np.ndarray, o: VideoObs, focal: float) -> np.ndarray:
    """centred: (N, 2) pixels from the principal point -> (N, 2) normalized with `focal` and `o.dist`."""
    if o.dist is None:
        return centred / focal
    K = np.array([[focal, 0, o.K[0, 2]], [0, focal, o.K[1, 2]], [0, 0, 1.0]])
    return normalize(centred + o.K[:2, 2], K, o.dist)


def _align_to_anchors(b: Bundle, videos: list[SubjectVideo], anchors: list[int]) -> None:
    """Similarity taking the solved frame to the anchors' (rotation from their orientations, scale from centres)."""
    Rs = [rotation(b.rvec[j]) for j in anchors]
    Ra = [np.asarray(videos[b.cams[j]].cam_from_world[0], dtype=float) for j in anchors]  # type: ignore[index]
    ta = [np.asarray(videos[b.cams[j]].cam_from_world[1], dtype=float) for j in anchors]  # type: ignore[index]
    M = sum(R_true.T @ R_est for R_true, R_est in zip(Ra, Rs, strict=True))  # world_true = Q world_est
    U, _, Vt = np.linalg.svd(M)
    Q = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    c_est = np.array([_centre(b, j) for j in anchors])
    c_true = np.array([-R.T @ t for R, t in zip(Ra, ta, strict=True)])
    if len(anchors) >= 2:
        a = (c_est - c_est.mean(0)) @ Q.T
        s = float((a * (c_true - c_true.mean(0))).sum() / max((a**2).sum(), 1e-12))
    else:
        s = 1.0
    T = c_true.mean(0) - s * c_est.mean(0) @ Q.T
    for j in range(len(b.cams)):
        R = rotation(b.rvec[j]) @ Q.T
        c = s * Q @ _centre(b, j) + T
        b.rvec[j] = rotation_vector(R)
        b.t[j] = -R @ c
    b.knots.X = s * b.knots.X @ Q.T + T
    for j, R, t in zip(anchors, Ra, ta, strict=True):
        b.rvec[j], b.t[j] = rotation_vector(R), t


def _apply_scale(b: Bundle, points: list[str], scale: tuple[str, str, float], anchors: list[int]) -> None:
    A, B = b.knots.X[:, points.index(scale[0])], b.knots.X[:, points.index(scale[1])]
    d = np.linalg.norm(A - B, axis=1)
    d = d[np.isfinite(d)]
    if not len(d):
        raise ScalePointsError(
            f"points {scale[0]} and {scale[1]} are never triangulated together; "
            "choose scale points seen at the same time"
        )
    s = scale[2] / float(np.mean(d))
    centre = _centre(b, anchors[0]) if anchors else np.zeros(3)  # a single anchor stays where it is
    for j in range(len(b.cams)):
        R = rotation(b.rvec[j])
        c = centre + s * (_centre(b, j) - centre)
        b.t[j] = -R @ c
    b.knots.X = centre + s * (b.knots.X - centre)
