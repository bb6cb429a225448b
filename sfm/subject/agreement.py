"""Do the static cameras' known poses agree with the moving subject? A check of the background's model.

Background SfM can build a model from consistent false matches (repeated plates, posters, wallpaper): the model is
registered, and wrong. Static cameras far apart give it few true matches to outvote them. Where the subject is
tracked in two static videos that the background posed, its correspondences give an independent epipolar geometry:
per pair, the time offset and an essential matrix are fitted to the tracks alone (`pairs.fit_pair`; a pair whose
offset the tracks do not single out by `CLEAR_RATIO` is not checked, since it pairs other instants), and the
background's relative pose is scored on the correspondences at its own best offset (any offset the videos' tracks
overlap at, wherever the tracks' is). A pose that leaves the subject `MAX_RATIO` times further from its epipolar
lines than the tracks' own geometry, and by more than `MIN_PX`, contradicts it. Videos in contradicted pairs are
refuted greedily: the one in most of them first, until no contradicted pair remains among the rest (both of a lone
pair: which one is wrong cannot be told). A pose whose intrinsics are no lens's (a focal outside `FOCAL_RANGE` times
the image's long side) is refuted as it stands.

It is a garbage detector, not an accuracy bound: its limits leave room for tracks as noisy as joint detections,
whose own geometry is no better than a background pose a little off (docs/registration.md, "Measured").
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dynrecon.jsonvalues import finite_or_none
from sfm.options import MAX_OFFSET_S
from sfm.subject.geometry import sampson
from sfm.subject.model import MIN_SHARED, NOISE_SCALES_PX, SEED, SubjectVideo
from sfm.subject.observations import VideoObs, build_observations
from sfm.subject.pairs import correspondences, fit_pair, pair_correspondences, search_range
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

MAX_RATIO = 5.0  # a contradicted pose leaves the subject this many times further from its epipolar lines ...
MIN_PX = 3.0  # ... and more than this further (image pixels: a wrong focal scales angles, not what was measured)
CLEAR_RATIO = 1.15  # the tracks' offset must beat any other a frame away by this (the one-point pairs' margin)
OWN_FIT_PX = max(NOISE_SCALES_PX)  # ... and their own geometry fit half its correspondences within this (median)
SHIFT_REACH = 1.0  # the poses' best offset: fine steps this many frame periods around each coarse candidate
SHIFT_STEP = 0.25  # in frame periods of the faster video
COARSE_CORRESPONDENCES = 2000  # at most (every k-th frame of a) in the coarse scan of the poses' offset
FINE_PEAKS = 5  # coarse candidates searched finely
CHUNK = 64  # shifts scored at once
# the poses' offset needs this share of the correspondences the tracks' offset has: a short overlap at a far offset
# lets a wrong pose fit a few of them
MIN_SHARE = 0.25
TIE = 0.05  # mean log ratios closer than this do not tell two videos apart
# focal (in units of the image's long side) of any lens: a fisheye's about 0.15, a 30x zoom's about 25
FOCAL_RANGE = (0.1, 30.0)
MIN_BASELINE = 1e-9  # relative: two poses at one centre (no epipolar geometry) are not checked


@dataclass(kw_only=True)
class PairAgreement:
    """One pair of posed videos against the subject's tracks; distances are medians over the correspondences, in
    pixels (normalized distance times the pair's mean focal)."""

    a: str
    b: str
    checked: bool
    why: str | None = None  # why it was not checked
    offset_s: float | None = None  # o_b - o_a from the tracks (global = own + o)
    tracks_px: float | None = None  # with the tracks' own epipolar geometry
    poses_px: float | None = None  # with the poses' epipolar geometry
    correspondences: int = 0
    poses_offset_s: float | None = None  # o_b - o_a where the poses fit the subject best
    contradicted: bool = False

    def to_json(self) -> dict[str, Any]:
        return {
            "a": self.a,
            "b": self.b,
            "checked": self.checked,
            "why": self.why,
            "offset_s": finite_or_none(self.offset_s),
            "tracks_px": finite_or_none(self.tracks_px),
            "poses_px": finite_or_none(self.poses_px),
            "correspondences": self.correspondences,
            "poses_offset_s": finite_or_none(self.poses_offset_s),
            "contradicted": self.contradicted,
        }


@dataclass(kw_only=True)
class Agreement:
    pairs: list[PairAgreement] = field(default_factory=list)
    refuted: dict[str, str] = field(default_factory=dict)  # video -> why its pose is refuted

    def to_json(self) -> dict[str, Any]:
        return {
            "pairs": [p.to_json() for p in self.pairs],
            "refuted": dict(self.refuted),
            "limits": {"max_ratio": MAX_RATIO, "min_px": MIN_PX},
        }


def check_agreement(tracks: Tracks, videos: list[SubjectVideo], max_offset: float = MAX_OFFSET_S) -> Agreement:
    """Check every pair of `videos` (each with `K` and `cam_from_world`) against the subject's `tracks`."""
    for video in videos:
        if video.K is None or video.cam_from_world is None:
            raise ValueError(f"{video.name}: a pose and intrinsics are needed to check it")
    _, obs = build_observations(tracks, videos)
    rng = np.random.default_rng(SEED)
    result = Agreement()
    lens = {v.name: why for v in videos if (why := _no_lens(v)) is not None}
    for a, b in itertools.combinations(range(len(videos)), 2):
        if obs[a].name in lens or obs[b].name in lens:
            why = f"{obs[a].name if obs[a].name in lens else obs[b].name}'s intrinsics are no lens"
            result.pairs.append(PairAgreement(a=obs[a].name, b=obs[b].name, checked=False, why=why))
            continue
        result.pairs.append(_check_pair(obs[a], obs[b], a, b, max_offset, rng))
    result.refuted = {**lens, **_refute(result.pairs)}
    return result


def _no_lens(video: SubjectVideo) -> str | None:
    """Why the video's intrinsics cannot be a camera's (a focal far outside any lens's), or None."""
    assert video.K is not None
    return no_lens(video.K, video.width, video.height)


def no_lens(K: np.ndarray, width: int, height: int) -> str | None:
    """Why intrinsics `K` cannot be those of a camera whose images are `width` x `height` (a focal far outside any
    lens's, from fisheye to long telephoto), or None."""
    focal, side = float(np.sqrt(abs(K[0, 0] * K[1, 1]))), float(max(width, height))
    if FOCAL_RANGE[0] * side <= focal <= FOCAL_RANGE[1] * side:
        return None
    return (
        f"its intrinsics are no lens: a focal of {focal:.0f} px for a {side:.0f} px image (outside "
        f"{FOCAL_RANGE[0]:g}-{FOCAL_RANGE[1]:g} x), a model fitted to false matches"
    )


def _check_pair(
    oa: VideoObs, ob: VideoObs, a: int, b: int, max_offset: float, rng: np.random.Generator
) -> PairAgreement:
    out = PairAgreement(a=oa.name, b=ob.name, checked=False)
    if oa.count() == 0 or ob.count() == 0:
        out.why = f"{oa.name if oa.count() == 0 else ob.name} has no tracks"
        return out
    assert oa.video.cam_from_world is not None and ob.video.cam_from_world is not None
    Ra, ta = oa.video.cam_from_world
    Rb, tb = ob.video.cam_from_world
    R = Rb @ Ra.T
    t = tb - R @ ta
    size = max(float(np.linalg.norm(ta)), float(np.linalg.norm(tb)), 1.0)
    if np.linalg.norm(t) <= MIN_BASELINE * size:
        out.why = "the two poses share one centre (no epipolar geometry)"
        return out
    fit = fit_pair(oa, ob, a, b, max_offset, rng)
    if not fit.usable or fit.E is None:
        out.why = f"the tracks do not determine the pair: {fit.reason or fit.degenerate}"
        return out
    if fit.ambiguous or fit.runner_up_ratio < CLEAR_RATIO:
        # an offset the tracks do not single out (one point, tracks that never overlap at the true offset) pairs
        # other instants, which the tracks' own E fits and right poses do not
        out.why = f"the tracks' time offset is not clear (runner-up ratio {fit.runner_up_ratio:.3g} < {CLEAR_RATIO})"
        return out
    focal = float(np.sqrt(oa.focal * ob.focal))
    xa, xb = correspondences(oa, ob, fit.shift)
    own = float(np.median(np.sqrt(sampson(fit.E[None], xa, xb)[0])))
    if own * focal > OWN_FIT_PX:
        # the tracks' own geometry leaves most correspondences off its lines: their offset pairs other instants
        out.why = f"the tracks' own geometry fits them at {own * focal:.1f} px (> {OWN_FIT_PX:g}): offset not clear"
        return out
    tx = t / np.linalg.norm(t)
    E = np.array([[0, -tx[2], tx[1]], [tx[2], 0, -tx[0]], [-tx[1], tx[0], 0]]) @ R
    least = max(MIN_SHARED, int(MIN_SHARE * len(xa)))
    poses, shift = _poses_best(oa, ob, E, fit.shift, max_offset, least)
    out.checked = True
    out.offset_s = -fit.shift  # own_b = own_a + shift at one instant: o_b - o_a = -shift
    out.poses_offset_s = -shift
    out.tracks_px, out.poses_px, out.correspondences = own * focal, poses * focal, len(xa)
    out.contradicted = bool(poses > MAX_RATIO * own and (poses - own) * focal > MIN_PX)
    return out


def _poses_best(
    oa: VideoObs, ob: VideoObs, E: np.ndarray, near: float, max_offset: float, least: int
) -> tuple[float, float]:
    """The poses' least median epipolar distance (normalized) over every time offset with `least` correspondences,
    and that offset (own_b = own_a + shift): their own best, wherever the tracks' offset is (a wrong one pairs other
    instants). A coarse scan a frame period apart on at most `COARSE_CORRESPONDENCES`, then the best few and the
    tracks' own offset `near` in steps of `SHIFT_STEP` periods."""
    period = min(oa.period, ob.period)
    lo, hi = search_range(oa, ob, max_offset)
    coarse = np.arange(lo, hi + period / 2, period)
    stride = max(1, oa.count() // COARSE_CORRESPONDENCES)
    starts = [near]
    if len(coarse):
        scores = np.concatenate(
            [_medians(oa, ob, E, coarse[i : i + CHUNK], stride, least // stride) for i in range(0, len(coarse), CHUNK)]
        )
        order = np.argsort(scores)[:FINE_PEAKS]
        starts += [float(c) for c in coarse[order][np.isfinite(scores[order])]]
    fine = np.concatenate(
        [s + np.arange(-SHIFT_REACH, SHIFT_REACH + SHIFT_STEP / 2, SHIFT_STEP) * period for s in starts]
    )
    scores = np.concatenate([_medians(oa, ob, E, fine[i : i + CHUNK], 1, least) for i in range(0, len(fine), CHUNK)])
    best = int(np.argmin(scores))
    return float(scores[best]), float(fine[best])


def _medians(oa: VideoObs, ob: VideoObs, E: np.ndarray, shifts: np.ndarray, stride: int, least: int) -> np.ndarray:
    """(D,) median epipolar distance (normalized) of the correspondences at each shift; inf with fewer than `least`
    of them."""
    xa, xb = pair_correspondences(oa, ob, shifts, stride)  # (D, M, 2) with NaN
    distance = np.sqrt(sampson(E[None], xa, xb)[:, 0])  # (D, M), NaN where either side is unobserved
    valid = np.isfinite(distance)
    out = np.full(len(shifts), np.inf)
    enough = valid.sum(axis=1) >= max(least, 8)
    if enough.any():
        out[enough] = np.nanmedian(distance[enough], axis=1)
    return out


def _refute(pairs: list[PairAgreement]) -> dict[str, str]:
    """The videos whose poses go: the one in most contradicted pairs first, until none is left among the rest. Of
    videos in as many, the one whose checked pairs fit worst on the whole (the mean log ratio of the poses' distance
    to the tracks' own) goes; both of a pair that nothing else tells apart."""
    checked = [p for p in pairs if p.checked and p.tracks_px and p.poses_px is not None]
    refuted: dict[str, str] = {}
    while True:
        left = [p for p in checked if p.contradicted and p.a not in refuted and p.b not in refuted]
        if not left:
            return refuted
        count: dict[str, int] = {}
        for pair in left:
            for name in (pair.a, pair.b):
                count[name] = count.get(name, 0) + 1
        most = max(count.values())
        tied = [name for name, n in count.items() if n == most]
        fit = {name: _misfit(name, [p for p in checked if p.a not in refuted and p.b not in refuted]) for name in tied}
        worst = max(fit.values())
        for name in tied:
            if fit[name] < worst - TIE:
                continue
            pair = next(p for p in left if name in (p.a, p.b))
            other = pair.b if name == pair.a else pair.a
            refuted[name] = (
                f"its pose contradicts the subject's tracks: with {other}'s they lie {pair.poses_px:.1f} px from the "
                f"poses' epipolar lines, against {pair.tracks_px:.1f} px from the tracks' own epipolar geometry"
                + (f" ({most} such pairs)" if most > 1 else "")
            )


def _misfit(name: str, pairs: list[PairAgreement]) -> float:
    ratios = [np.log(max(p.poses_px or 0.0, 1e-12) / p.tracks_px) for p in pairs if name in (p.a, p.b) and p.tracks_px]
    return float(np.mean(ratios)) if ratios else 0.0
