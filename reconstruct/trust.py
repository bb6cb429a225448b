"""How much to trust each reconstructed point: per (frame, point) measures from the solve, and a flag for points
whose error is likely large.

Measures (arrays (F, P), NaN where the point was not reconstructed):
* `condition`: the paper's reconstructability (Sec. "Analysis", Eq. (A)) for the point in frame f's neighbourhood.
  The paper writes the error of a point's trajectory along its rays, l, as the solution of A l = b with
  A_gh = [(I - W)(I - W)^T]_gh r_g.r_h and bounds |l| <= |A^-1| |b| = |b| / sigma_min(A). Here the neighbourhood
  N = {f} + the strongest W neighbours of f (both directions) is unknown and every other frame is held at its
  value: A_N is the principal submatrix of the paper's A on N, and `condition` = 1 / sigma_min(A_N) bounds how much
  a self-expression misfit in that neighbourhood is amplified along the rays. A frame where the point is not
  observed has no ray: its error has 3 degrees of freedom (the identity instead of r), as in the paper's
  "Missing data". Dimensionless (W and rays are).
* `residual`: |X_pf - sum_j W_jf X_pj|, the point's own self-expression residual (paper, Sec. "Shape approximation
  residual"; it stands in for the b of the bound above, which needs the truth), input units. `residual_px`: the
  same seen from frame f's camera (focal x residual / distance), pixels. `bound_px` = condition x residual_px.
* `ray_distance`: distance of X_pf from its viewing ray (the soft ray constraint lets it leave), input units; NaN
  where unobserved. `reprojection_px` is the same as an angle seen from the camera, in pixels (x focal length).
* `support`: share of frame f's W weight on neighbours that observe the point (1 = interpolated between
  observations; 0 = a missing point built only from other missing points, i.e. extrapolated).
* `videos`: number of distinct videos among frame f's neighbours (per frame, repeated for every point).
* `sequence_jump`: how far the local sequencing recovered by W breaks at frame f (per frame; see `sequence_jump`).
* `component`: frames in frame f's connected component of the W graph (per frame; small = an island, see
  `components`).
* `smoothness`, `smoothness_px`: distance from the interpolation of the point's previous and next frame in its own
  video (the paper's Psi2 as a check; see `video_smoothness`).
* `step_px`: the larger of the point's moves to its previous and next frame in its own video, pixels (see
  `video_step`); at a video's first and last frame (`video_end`) a fast point is extrapolated by W, not interpolated.

The flag (`flag`, bool) is a rule on these measures (`flag_points`); its thresholds live in TrustOptions, tuned on
simulations (benchmarks/trust.py) and on real tracking (benchmarks/trust_real.py); see docs/trust.md.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from dynrecon.jsonvalues import finite_or_none
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays
from reconstruct.views import SINGLE_VIEW, views_near

log = logging.getLogger(__name__)


# W entries below this are not neighbours (numerical dust of the W-step).
MIN_WEIGHT = 0.02
# Strongest neighbours kept per frame in a neighbourhood: the paper's W columns have about two.
MAX_NEIGHBOURS = 4


@dataclass(kw_only=True)
class TrustOptions:
    """The flag rule (`flag_rule`, `flag_points`); thresholds tuned on simulations (benchmarks/trust.py) and real
    tracking (benchmarks/trust_real.py).

    residual_px, bound_px, relative: a point is flagged when its residual in pixels, or that residual amplified by
    the condition (the paper's bound |l| <= |b| / sigma_min with the point's residual for |b|), exceeds the floor
    (`residual_px`, `bound_px`) and `relative` times its median over the solve's observed points (the median
    follows the noise level and frame rate: a scale-free limit).
    sequence_jump: ... or the local sequencing breaks by more than this many frame gaps (correct interpolation stays
    within a few; the paper's wrong-partner failure jumps by seconds).
    min_component: ... or the frame lies in a connected component of the W graph with fewer frames than this (0: not
    used): an island of frames that only represent each other (the paper's wrong partners). Off by default: islands
    are as often harmless (static phases) as wrong.
    smoothness_px, smoothness_relative: ... or the point leaves the interpolation of its own video's previous and next
    frame by more than max(smoothness_px, smoothness_relative x median) pixels (smoothness_px 0: not used; see
    `video_smoothness`). Off in the balanced preset: on the tuning windows it raised recall but lowered precision
    more.
    bound_relative: the multiple of the median for the bound (0: `relative`, as for the residual).
    sequence_relative: the sequence_jump limit is max(sequence_jump, sequence_relative x median sequence_jump) (0:
    the fixed limit alone); periodic motion legitimately links frames a cycle apart, which raises the median.
    min_support: ... or the point is unobserved and its support is below this (0: not used): a missing point built
    mostly from neighbours that miss it too, i.e. extrapolated (an observed point is held by its ray).
    end_step_relative: ... or, at a video's first or last frame, the point moves to its neighbouring frame by more
    than this x the median step_px (0: not used): W extrapolates a fast point at the capture's ends.
    video_relative: ... or its video's median residual_px exceeds max(`residual_px`, this x the median of the other
    videos' medians), with 3 videos or more (0: not used; `off_videos`): a whole video that the others' shapes do
    not explain follows another subject, or its camera or clock is wrong, and every point of it is suspect.
    min_views: ... or fewer videos than this observe the point near the frame's time (`views`, reconstruct/views.py;
    0: not used): its position lies along one camera's rays, at a depth no second view measured.
    reprojection_px, reprojection_relative: ... or the written point of an observed frame misses its own observation
    by more than max(reprojection_px, reprojection_relative x median) pixels (reprojection_px 0: not used): refined
    trajectories smooth through the rays, and where they cut a fast motion short (a bat's wing tips) the written
    point leaves its ray, which the other measures, computed on the trajectories, do not see.
    """

    residual_px: float = 5.0
    bound_px: float = 30.0
    relative: float = 3.0
    sequence_jump: float = 20.0
    min_component: int = 0
    smoothness_px: float = 0.0
    smoothness_relative: float = 5.0
    bound_relative: float = 0.0
    sequence_relative: float = 0.0
    min_support: float = 0.0
    end_step_relative: float = 0.0
    video_relative: float = 3.0
    min_views: int = SINGLE_VIEW
    reprojection_px: float = 0.0
    reprojection_relative: float = 5.0


class TrustPreset(enum.Enum):
    """Operating points of the flag (docs/trust.md has the tables)."""

    BALANCED = "balanced"  # TrustOptions() defaults: best recall-weighted F2 on the simulated tuning windows
    SENSITIVE = "sensitive"  # limits in units of the capture's own medians: tuned on real tracking and simulations


def preset_options(preset: TrustPreset) -> TrustOptions:
    if preset is TrustPreset.SENSITIVE:
        return TrustOptions(
            residual_px=1.5,
            bound_px=5.0,
            relative=2.5,
            bound_relative=4.0,
            sequence_jump=12.0,
            sequence_relative=3.0,
            smoothness_px=30.0,
            smoothness_relative=5.0,
            min_support=0.1,
            end_step_relative=2.0,
            reprojection_px=5.0,
            reprojection_relative=5.0,
        )
    return TrustOptions()


@dataclass(kw_only=True)
class Trust:
    condition: np.ndarray  # (F, P) dimensionless, 1 / sigma_min of the neighbourhood's A
    residual: np.ndarray  # (F, P) input units
    residual_px: np.ndarray  # (F, P) pixels, residual seen from frame f's camera
    bound_px: np.ndarray  # (F, P) pixels, condition x residual_px
    ray_distance: np.ndarray  # (F, P) input units, NaN where unobserved
    reprojection_px: np.ndarray  # (F, P) pixels, NaN where unobserved
    support: np.ndarray  # (F, P) in [0, 1]
    sequence_jump: np.ndarray  # (F, P) frame gaps, per frame (see `sequence_jump`), NaN where times are unknown
    component: np.ndarray  # (F, P) frames in the frame's connected component of the W graph (see `components`)
    smoothness: np.ndarray  # (F, P) input units, off the own video's interpolation (see `video_smoothness`)
    smoothness_px: np.ndarray  # (F, P) pixels, the same seen from frame f's camera
    step_px: np.ndarray  # (F, P) pixels, the larger move to the previous / next frame of its video (`video_step`)
    video_end: np.ndarray  # (F, P) bool, per frame: the first or last frame of its video (`video_ends`)
    videos: np.ndarray  # (F, P) distinct videos among the frame's neighbours
    views: np.ndarray  # (F, P) videos observing the point near the frame's time (reconstruct/views.py)
    flag: np.ndarray  # (F, P) bool, error likely large (False where not reconstructed)
    limits: dict[str, float]  # the rule's effective limits in this solve: residual_px, bound_px
    reconstructed: np.ndarray  # (F, P) bool
    video_names: list[str] = field(default_factory=list)  # (N,) for the per-video counts of the summary
    video_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (F,)
    # video name -> its median residual_px and the limit it broke (`off_videos`); all its points are flagged
    off_videos: dict[str, dict[str, float]] = field(default_factory=dict)
    options: TrustOptions = field(default_factory=TrustOptions)

    def columns(self) -> dict[str, np.ndarray]:
        """Extra columns of points3d.csv, name -> (F, P) floats (NaN = empty)."""
        empty = ~self.reconstructed
        return {
            "condition": _blank(self.condition, empty),
            "residual": _blank(self.residual, empty),
            "residual_px": _blank(self.residual_px, empty),
            "bound_px": _blank(self.bound_px, empty),
            "ray_distance": _blank(self.ray_distance, empty),
            "reprojection_px": _blank(self.reprojection_px, empty),
            "support": _blank(self.support, empty),
            "sequence_jump": _blank(self.sequence_jump, empty),
            "component": _blank(self.component, empty),
            "smoothness_px": _blank(self.smoothness_px, empty),
            "step_px": _blank(self.step_px, empty),
            "views": _blank(self.views, empty),
            "flag": np.where(empty, np.nan, self.flag.astype(float)),
        }

    def summary(self) -> dict[str, Any]:
        """The report.json `trust` block: distribution of each measure and the flag count."""
        done = self.reconstructed
        measures = {}
        for name, values in (
            ("condition", self.condition),
            ("residual", self.residual),
            ("residual_px", self.residual_px),
            ("bound_px", self.bound_px),
            ("ray_distance", self.ray_distance),
            ("reprojection_px", self.reprojection_px),
            ("support", self.support),
            ("sequence_jump", self.sequence_jump),
            ("component", self.component),
            ("smoothness", self.smoothness),
            ("smoothness_px", self.smoothness_px),
            ("step_px", self.step_px),
            ("views", self.views),
        ):
            v = values[done & np.isfinite(values)]
            measures[name] = {
                "median": finite_or_none(np.median(v)) if v.size else None,
                "p90": finite_or_none(np.percentile(v, 90)) if v.size else None,
                "max": finite_or_none(np.max(v)) if v.size else None,
            }
        flagged = int(np.sum(self.flag & done))
        total = int(done.sum())
        per_video = {}
        for v, name in enumerate(self.video_names):
            rows = self.video_index == v
            per_video[name] = {
                "flagged": int(np.sum(self.flag[rows] & done[rows])),
                "reconstructed": int(done[rows].sum()),
            }
        return {
            "units": {
                "condition": "dimensionless",
                "residual": "input units",
                "ray_distance": "input units",
                "residual_px": "pixels",
                "bound_px": "pixels",
                "reprojection_px": "pixels",
                "support": "fraction",
                "sequence_jump": "frame gaps",
                "component": "frames",
                "smoothness": "input units",
                "smoothness_px": "pixels",
                "step_px": "pixels",
                "views": "videos",
            },
            "measures": measures,
            "flagged": flagged,
            "reconstructed": total,
            "flagged_share": flagged / total if total else None,
            "single_view": int(np.sum(done & (self.views < SINGLE_VIEW))),
            "per_video": per_video,
            "off_videos": self.off_videos,
            "rule": flag_rule(self.options),
            "limits": {k: finite_or_none(v) for k, v in self.limits.items()},
            "options": asdict(self.options),
        }


def flag_rule(options: TrustOptions) -> str:
    k = f"{options.relative:g}"
    kb = f"{options.bound_relative or options.relative:g}"
    jump = (
        f"max({options.sequence_jump:g}, {options.sequence_relative:g} x median sequence_jump)"
        if options.sequence_relative > 0
        else f"{options.sequence_jump:g}"
    )
    return (
        f"residual_px > max({options.residual_px:g}, {k} x median residual_px) or "
        f"bound_px = condition x residual_px > max({options.bound_px:g}, {kb} x median bound_px) or "
        f"sequence_jump > {jump}"
        + (f" or (unobserved and support < {options.min_support:g})" if options.min_support > 0 else "")
        + (
            f" or (first or last frame of its video and step_px > {options.end_step_relative:g} x median step_px)"
            if options.end_step_relative > 0
            else ""
        )
        + (f" or component < {options.min_component}" if options.min_component > 0 else "")
        + (
            f" or its video's median residual_px > max({options.residual_px:g}, {options.video_relative:g} x the "
            "other videos' median) (3+ videos)"
            if options.video_relative > 0
            else ""
        )
        + (
            f" or smoothness_px > max({options.smoothness_px:g}, {options.smoothness_relative:g} x median "
            "smoothness_px)"
            if options.smoothness_px > 0
            else ""
        )
        + (f" or views < {options.min_views}" if options.min_views > 0 else "")
        + (
            f" or (observed and reprojection_px > max({options.reprojection_px:g}, {options.reprojection_relative:g} x "
            "median reprojection_px))"
            if options.reprojection_px > 0
            else ""
        )
        + "; medians over the solve's observed points"
    )


def _blank(values: np.ndarray, empty: np.ndarray) -> np.ndarray:
    return np.where(empty, np.nan, values)


def neighbourhoods(W: sp.csc_matrix, min_weight: float, max_neighbours: int) -> np.ndarray:
    """(F, 1 + max_neighbours) frame indices: f itself, then its strongest neighbours in W (W_jf or W_fj above
    `min_weight`, by weight), padded with -1."""
    F = W.shape[0]
    both = W.maximum(W.T).tocsc()
    out = np.full((F, 1 + max_neighbours), -1, dtype=np.int64)
    out[:, 0] = np.arange(F)
    for f in range(F):
        start, stop = both.indptr[f], both.indptr[f + 1]
        rows, values = both.indices[start:stop], both.data[start:stop]
        keep = values >= min_weight
        rows, values = rows[keep], values[keep]
        chosen = rows[np.argsort(-values, kind="stable")[:max_neighbours]]
        out[f, 1 : 1 + len(chosen)] = chosen
    return out


def neighbourhood_condition(gram: np.ndarray, rays: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """1 / sigma_min of the paper's A for neighbourhoods, batched.

    gram: (B, n, n) [(I - W)(I - W)^T] restricted to each neighbourhood; rays: (B, n, 3) unit rays, NaN where the
    point is unobserved (3 free coordinates); valid: (B, n) slots in use (default all). Returns (B,).

    A_gh = gram_gh B_g^T B_h with B_g = r_g (observed) or I (unobserved). Where every slot in use is observed, A is
    n x n, gram_gh (r_g . r_h) (`_observed_smallest`); elsewhere the 3n x 3n construction (`_general_smallest`).
    Both fill what is not A with c, above A's largest eigenvalue, so that the smallest eigenvalue is A's. A
    singular A (e.g. all rays parallel in a closed group) gives ~1e13 / c.
    """
    B, n = gram.shape[:2]
    valid = np.ones((B, n), dtype=bool) if valid is None else valid
    observed = np.isfinite(rays).all(axis=-1)  # (B, n)
    simple = np.all(observed | ~valid, axis=1)
    smallest, c = np.empty(B), np.empty(B)
    if simple.any():
        smallest[simple], c[simple] = _observed_smallest(gram[simple], np.nan_to_num(rays[simple]), valid[simple])
    if not simple.all():
        general = ~simple
        smallest[general], c[general] = _general_smallest(
            gram[general], rays[general], observed[general], valid[general]
        )
    # Below 1e-13 c the eigenvalue is rounding noise: a singular system reads as a huge but finite condition.
    return 1.0 / np.maximum(smallest, 1e-13 * c)


def _observed_smallest(gram: np.ndarray, rays: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A's smallest eigenvalue and c, (B,) each, where every slot in use is observed: A = gram o (r r^T), n x n,
    with c on the diagonal of unused slots (a 3n x 3n eigenproblem becomes n x n)."""
    n = gram.shape[1]
    dots = np.einsum("bgk,bhk->bgh", rays, rays)
    used = valid[:, :, None] & valid[:, None, :]
    A = np.where(used, gram * dots, 0.0)
    c = np.einsum("bgg->b", A) + 1.0  # trace >= largest eigenvalue of a PSD matrix, as in `_general_smallest`
    A[:, np.arange(n), np.arange(n)] += np.where(valid, 0.0, c[:, None])
    return np.linalg.eigvalsh(A)[:, 0], c


def _general_smallest(
    gram: np.ndarray, rays: np.ndarray, observed: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A's smallest eigenvalue and c, (B,) each, for any observation pattern: the 3n x 3n matrix gram_gh P_g P_h
    (P_g = B_g B_g^T) plus c (I - P) on the complement (and on unused slots), which has the eigenvalues of A and c."""
    B, n = gram.shape[:2]
    r = np.nan_to_num(rays)
    projector = np.where(observed[..., None, None], r[..., :, None] * r[..., None, :], np.eye(3))  # (B, n, 3, 3)
    projector = np.where(valid[..., None, None], projector, 0.0)
    # Built with the batch axis last (long inner loops) as big[g, i, h, k, b] = gram_gh [P_g P_h]_ik, the 3n x 3n
    # matrix; every sum runs in ascending order from zero, as einsum sums it: the same bits, so the same eigenvalues.
    Q = np.ascontiguousarray(projector.transpose(1, 2, 3, 0))  # (n, 3, 3, B)
    big = np.zeros((n, 3, n, 3, B))
    for j in range(3):
        big += Q[:, :, None, None, j, :] * Q[None, None, :, j, :, :]
    big *= gram.transpose(1, 2, 0)[:, None, :, None, :]
    idx = np.arange(n)
    c = np.einsum("gigib->b", big) + 1.0  # trace >= largest eigenvalue of a PSD matrix
    big += 0.0  # off the diagonal blocks the complement adds c x 0: a -0.0 becomes 0.0
    big[idx, :, idx, :, :] += c * (np.eye(3)[:, :, None] - Q)
    matrices = np.ascontiguousarray(big.transpose(4, 0, 1, 2, 3)).reshape(B, 3 * n, 3 * n)
    return np.linalg.eigvalsh(matrices)[:, 0], c


def components(W: sp.csc_matrix, min_weight: float) -> np.ndarray:
    """(F,) number of frames in each frame's connected component of the graph linking f and j when W_jf or W_fj is
    at least `min_weight`. A correct solve chains every frame to its temporal neighbours in one large component."""
    linked = W.maximum(W.T).tocsr()
    linked.data[linked.data < min_weight] = 0.0
    linked.eliminate_zeros()
    _, label = connected_components(linked, directed=False)
    return np.bincount(label)[label]


def sequence_jump(W: sp.csc_matrix, video_index: np.ndarray, times: np.ndarray, min_mass: float = 0.2) -> np.ndarray:
    """(F,) how far the local sequencing breaks at each frame, in frame gaps; NaN where times are unknown.

    Frames f, f' consecutive in one video advance by dt = t_f' - t_f. Their neighbours in another video u (weighted
    mean time tau_u, where at least `min_mass` of the column's weight lies in u) should advance by about the same:
    |(tau_u(f') - tau_u(f)) - dt| stays within ~2 frame gaps when W interpolates between temporally close frames,
    and is of the order of seconds when a run of frames is expressed by shapes from elsewhere in the motion (the
    paper's "incorrect initialization" with periodic motion: two far-apart shapes representing each other). Only
    differences of times within a video are used, so the videos' unknown clock offsets do not matter. The gap unit
    is max(dt, median frame gap of the video, of u). The value of a frame is the largest over other videos and
    over its two sides (previous and next frame of its video).
    """
    F = W.shape[0]
    videos = int(video_index.max()) + 1 if F else 0
    rows, cols = W.nonzero()
    values = np.asarray(W[rows, cols]).ravel()
    mass = np.zeros((F, videos))
    weighted = np.zeros((F, videos))
    np.add.at(mass, (cols, video_index[rows]), values)
    np.add.at(weighted, (cols, video_index[rows]), values * times[rows])
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = np.where(mass >= min_mass, weighted / mass, np.nan)  # (F, videos)
    order = {}
    typical = np.full(videos, np.nan)
    for v in range(videos):
        frames = np.flatnonzero(video_index == v)
        frames = frames[np.argsort(times[frames], kind="stable")]
        order[v] = frames
        if len(frames) > 1:
            typical[v] = float(np.median(np.diff(times[frames])))
    out = np.full(F, np.nan)
    for v, frames in order.items():
        if len(frames) < 2:
            continue
        dt = np.diff(times[frames])  # (n - 1,)
        unit = np.fmax(np.fmax(dt, typical[v])[:, None], typical[None, :])  # (n - 1, videos)
        mismatch = np.abs(np.diff(tau[frames], axis=0) - dt[:, None]) / unit
        known = np.isfinite(mismatch).any(axis=1)
        step = np.where(known, np.nanmax(np.where(np.isfinite(mismatch), mismatch, -np.inf), axis=1), np.nan)
        side = np.full(len(frames), np.nan)
        side[:-1] = step
        side[1:] = np.fmax(side[1:], step)
        out[frames] = side
    return out


def video_smoothness(points: np.ndarray, video_index: np.ndarray, frames: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(F, P) distance of each point from the linear interpolation of the same point in the previous and next frame
    of its own video (input units); NaN at a video's first and last frame. The paper's Psi2 as a check: W never
    links frames of one video, so a shape that jumps away from its own video's neighbours (a run of frames expressed
    by shapes from elsewhere in the motion) shows here even when its self-expression residual is small. Times
    interpolate when known, frame numbers otherwise."""
    out = np.full(points.shape[:2], np.nan)
    clock = np.where(np.isfinite(times), times, frames.astype(float))
    for v in np.unique(video_index):
        members = np.flatnonzero(video_index == v)
        members = members[np.argsort(frames[members], kind="stable")]
        if len(members) < 3:
            continue
        previous, current, following = members[:-2], members[1:-1], members[2:]
        span = clock[following] - clock[previous]
        share = np.where(span > 0, (clock[current] - clock[previous]) / np.where(span > 0, span, 1.0), 0.5)
        predicted = points[previous] + share[:, None, None] * (points[following] - points[previous])
        out[current] = np.linalg.norm(points[current] - predicted, axis=-1)
    return out


def video_step(points: np.ndarray, video_index: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(F, P) the larger of the point's moves to the same point in the previous and the next frame of its own video
    (input units); NaN for a video of one frame."""
    out = np.full(points.shape[:2], np.nan)
    for v in np.unique(video_index):
        members = np.flatnonzero(video_index == v)
        members = members[np.argsort(frames[members], kind="stable")]
        if len(members) < 2:
            continue
        move = np.linalg.norm(np.diff(points[members], axis=0), axis=-1)  # (n - 1, P)
        step = np.full((len(members), points.shape[1]), np.nan)
        step[1:] = move
        step[:-1] = np.fmax(step[:-1], move)
        out[members] = step
    return out


def video_ends(video_names: list[str] | np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(F,) bool: the frame is the first or the last (by frame number) of its video."""
    names = np.asarray(video_names)
    out = np.zeros(len(names), dtype=bool)
    for v in np.unique(names):
        members = np.flatnonzero(names == v)
        out[members[np.argmin(frames[members])]] = True
        out[members[np.argmax(frames[members])]] = True
    return out


def trust_measures(
    problem: Problem, result: SolveResult, options: TrustOptions | None = None, times: np.ndarray | None = None
) -> Trust:
    """All measures for every (frame, point) of a solve, and the flag. `times` (F,): the frames' global times (the
    recovered clocks), which place the other videos' observations near a frame (`views`); None or NaN: the frame's
    self-expression neighbours do."""
    options = options or TrustOptions()
    F, P = problem.num_frames, problem.num_points
    points = result.points  # (F, P, 3) input units
    reconstructed = np.isfinite(points).all(axis=-1)
    rays = viewing_rays(problem)  # (F, P, 3)
    W = result.W.to_csc()
    focal = 0.5 * (problem.K[:, 0, 0] + problem.K[:, 1, 1])  # (F,)
    offset = points - problem.centers[:, None, :]
    depth = np.linalg.norm(offset, axis=-1)
    residual, residual_px = _self_expression(points, W, focal, depth)
    ray_distance, reprojection_px = ray_distances(offset, rays, problem.observed, focal)
    # Support: W weight on neighbours observing the point.
    support = np.asarray(W.T @ problem.observed.astype(float))
    support = np.clip(support / np.maximum(np.asarray(W.sum(axis=0)).reshape(-1, 1), 1e-300), 0.0, 1.0)
    hood = neighbourhoods(W, MIN_WEIGHT, MAX_NEIGHBOURS)  # (F, n)
    valid = hood >= 0
    videos = np.array([len(set(problem.video_index[hood[f, 1:][valid[f, 1:]]].tolist())) for f in range(F)])
    condition = _conditions(W, rays, reconstructed, hood)
    bound_px = condition * residual_px
    jump = np.broadcast_to(sequence_jump(W, problem.video_index, problem.times)[:, None], (F, P))
    component = np.broadcast_to(components(W, MIN_WEIGHT)[:, None], (F, P))
    smoothness = video_smoothness(points, problem.video_index, problem.frames, problem.times)
    smoothness_px = focal[:, None] * smoothness / np.maximum(depth, 1e-300)
    step_px = focal[:, None] * video_step(points, problem.video_index, problem.frames) / np.maximum(depth, 1e-300)
    end = np.broadcast_to(video_ends(problem.video_index, problem.frames)[:, None], (F, P))
    at = np.full(F, np.nan) if times is None else np.asarray(times, dtype=float)
    views = views_near(problem.video_index, at, problem.observed, hood)
    flag, limits = flag_points(
        options,
        reconstructed,
        {
            "residual_px": residual_px,
            "bound_px": bound_px,
            "sequence_jump": jump,
            "component": component,
            "smoothness_px": smoothness_px,
            "support": support,
            "observed": problem.observed,
            "step_px": step_px,
            "video_end": end,
            "views": views,
            "reprojection_px": reprojection_px,
        },
    )
    off = flag_off_videos(options, flag, reconstructed, problem.observed, residual_px, problem.video_index)
    # a person's tracks may be another person's; one tracked object (a ball, a marker) has no --person to choose
    other = "another object" if problem.num_points == 1 else "another subject (import-tracks --person)"
    for v, (median, limit) in off.items():
        log.warning(
            "trust: %s: its points miss what the other videos see by %.1f px (median residual), over %.1f px: "
            "its tracks may follow %s, or its camera or clock is wrong; every point of it is flagged",
            problem.video_names[v],
            median,
            limit,
            other,
        )
    log.info(
        "trust: %d of %d reconstructed points flagged (%s)",
        int(flag.sum()),
        int(reconstructed.sum()),
        flag_rule(options),
    )
    nan = ~reconstructed
    return Trust(
        condition=np.where(nan, np.nan, condition),
        residual=np.where(nan, np.nan, residual),
        residual_px=np.where(nan, np.nan, residual_px),
        bound_px=np.where(nan, np.nan, bound_px),
        ray_distance=np.where(nan, np.nan, ray_distance),
        reprojection_px=np.where(nan, np.nan, reprojection_px),
        support=np.where(nan, np.nan, support),
        sequence_jump=np.where(nan, np.nan, jump),
        component=np.where(nan, np.nan, component),
        smoothness=np.where(nan, np.nan, smoothness),
        smoothness_px=np.where(nan, np.nan, smoothness_px),
        step_px=np.where(nan, np.nan, step_px),
        video_end=end & reconstructed,
        videos=np.broadcast_to(videos[:, None], (F, P)).astype(float),
        views=np.where(nan, np.nan, views),
        flag=flag,
        limits=limits,
        reconstructed=reconstructed,
        video_names=list(problem.video_names),
        video_index=problem.video_index.copy(),
        off_videos={
            problem.video_names[v]: {"median_residual_px": float(m), "limit_px": float(lim)}
            for v, (m, lim) in off.items()
        },
        options=options,
    )


def _self_expression(
    points: np.ndarray, W: sp.csc_matrix, focal: np.ndarray, depth: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(F, P) each point's self-expression residual, in input units and seen from its frame's camera in pixels."""
    F, P = points.shape[:2]
    shapes = np.nan_to_num(points).reshape(F, -1)
    fit = (W.T @ shapes).reshape(F, P, 3)
    residual = np.linalg.norm(np.nan_to_num(points) - fit, axis=-1)
    return residual, focal[:, None] * residual / np.maximum(depth, 1e-300)


def ray_distances(
    offset: np.ndarray, rays: np.ndarray, observed: np.ndarray, focal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(F, P) distance from the viewing ray (input units) and that angle in pixels; NaN where unobserved."""
    along = np.sum(offset * rays, axis=-1)
    perpendicular = np.linalg.norm(offset - along[..., None] * rays, axis=-1)
    ray_distance = np.where(observed, perpendicular, np.nan)
    reprojection_px = np.where(observed, focal[:, None] * np.arctan2(perpendicular, np.maximum(along, 1e-300)), np.nan)
    return ray_distance, reprojection_px


def _conditions(W: sp.csc_matrix, rays: np.ndarray, reconstructed: np.ndarray, hood: np.ndarray) -> np.ndarray:
    """(F, P) the paper's A per point on each frame's neighbourhood `hood` (F, n): 1 / sigma_min."""
    F, P = reconstructed.shape
    valid = hood >= 0
    safe = np.where(valid, hood, 0)
    M = (sp.identity(F, format="csc") - W).tocsr()
    gram = _gram_blocks((M @ M.T).tocsr(), hood)
    condition = np.full((F, P), np.nan)
    for p in range(P):
        # only reconstructed points: elsewhere the measures are blanked
        rows = np.flatnonzero(reconstructed[:, p])
        if rows.size == F:
            condition[:, p] = neighbourhood_condition(gram, rays[safe, p], valid)
        elif rows.size:
            condition[rows, p] = neighbourhood_condition(gram[rows], rays[safe[rows], p], valid[rows])
    return condition


def _gram_blocks(G: sp.csr_matrix, hood: np.ndarray) -> np.ndarray:
    """(F, n, n) G restricted to each frame's neighbourhood `hood` (F, n; valid slots first, -1 after them): entry
    (f, g, h) is G[hood[f, g], hood[f, h]], 0 on unused slots. Looked up in G's sorted (row, column) keys at once."""
    F, n = hood.shape
    G = G.copy()
    G.sum_duplicates()  # canonical: one sorted entry per (row, column)
    keys = np.repeat(np.arange(G.shape[0], dtype=np.int64), np.diff(G.indptr)) * G.shape[1] + G.indices
    valid = hood >= 0
    safe = np.where(valid, hood, 0)
    wanted = safe[:, :, None] * G.shape[1] + safe[:, None, :]  # (F, n, n)
    at = np.minimum(np.searchsorted(keys, wanted), max(len(keys) - 1, 0))
    found = valid[:, :, None] & valid[:, None, :]
    if len(keys):
        found &= keys[at] == wanted
        return np.where(found, G.data[at], 0.0)
    return np.zeros((F, n, n))


def flag_points(
    options: TrustOptions, reconstructed: np.ndarray, measures: Mapping[str, np.ndarray]
) -> tuple[np.ndarray, dict[str, float]]:
    """The flag rule's verdict (shape of `reconstructed`) and its effective limits in this solve.

    measures: the rule's inputs by their points3d.csv column names (residual_px, bound_px, sequence_jump, component,
    smoothness_px, support, step_px; views and reprojection_px where present), `observed` and `video_end` (bool,
    `video_ends`), each of the shape of `reconstructed`; so the rule can be re-run on a written points3d.csv
    (benchmarks/trust_real.py).
    Every limit is the larger of a floor and a multiple of the measure's median over the solve's observed points
    (all reconstructed points where none is): the median is the capture's own noise level, which lives in the
    observations (unobserved points follow their neighbours; where they are most of a solve, their median would set
    the limit below the noise)."""
    residual_px, bound_px = measures["residual_px"], measures["bound_px"]
    jump, component, smoothness_px = measures["sequence_jump"], measures["component"], measures["smoothness_px"]

    observed = reconstructed & measures["observed"].astype(bool)
    scale = observed if observed.any() else reconstructed

    def median(values: np.ndarray) -> float:
        known = scale & np.isfinite(values)
        return float(np.median(values[known])) if known.any() else 0.0

    limits = {
        "residual_px": max(options.residual_px, options.relative * median(residual_px)),
        "bound_px": max(options.bound_px, (options.bound_relative or options.relative) * median(bound_px)),
        "sequence_jump": max(options.sequence_jump, options.sequence_relative * median(jump)),
    }
    flag = reconstructed & (
        (residual_px > limits["residual_px"])
        | (bound_px > limits["bound_px"])
        | (np.nan_to_num(jump) > limits["sequence_jump"])
        | (component < options.min_component)
    )
    if options.smoothness_px > 0:
        limits["smoothness_px"] = max(options.smoothness_px, options.smoothness_relative * median(smoothness_px))
        flag |= reconstructed & (np.nan_to_num(smoothness_px) > limits["smoothness_px"])
    if options.min_support > 0:
        missing = reconstructed & ~measures["observed"].astype(bool)
        flag |= missing & (np.nan_to_num(measures["support"], nan=1.0) < options.min_support)
    if options.min_views > 0 and "views" in measures:  # a points3d.csv written before the column had none
        flag |= reconstructed & (np.nan_to_num(measures["views"], nan=np.inf) < options.min_views)
    if options.reprojection_px > 0 and "reprojection_px" in measures:
        reprojection = measures["reprojection_px"]
        limits["reprojection_px"] = max(options.reprojection_px, options.reprojection_relative * median(reprojection))
        flag |= observed & (np.nan_to_num(reprojection) > limits["reprojection_px"])
    if options.end_step_relative > 0:
        step_px = measures["step_px"]
        limits["step_px"] = options.end_step_relative * median(step_px)
        flag |= reconstructed & measures["video_end"] & (np.nan_to_num(step_px) > limits["step_px"])
    return flag, limits


def off_videos(
    options: TrustOptions, reconstructed: np.ndarray, residual_px: np.ndarray, video_index: np.ndarray
) -> dict[int, tuple[float, float]]:
    """Videos whose points the other videos' shapes do not explain: video index -> (its median residual_px over
    `reconstructed`, the limit it exceeds), the limit being max(`options.residual_px`, `options.video_relative` x
    the median of the other videos' medians). Needs 3 videos with points (with 2, neither can be told to be the odd
    one).

    reconstructed, residual_px: (F, P); video_index: (F,)."""
    if options.video_relative <= 0:
        return {}
    medians = {}
    for v in np.unique(video_index):
        own = video_index == v
        known = reconstructed[own] & np.isfinite(residual_px[own])
        if known.any():
            medians[int(v)] = float(np.median(residual_px[own][known]))
    if len(medians) < 3:
        return {}
    out = {}
    for v, median in medians.items():
        others = float(np.median([m for u, m in medians.items() if u != v]))
        limit = max(options.residual_px, options.video_relative * others)
        if median > limit:
            out[v] = (median, limit)
    return out


def flag_off_videos(
    options: TrustOptions,
    flag: np.ndarray,
    reconstructed: np.ndarray,
    observed: np.ndarray,
    residual_px: np.ndarray,
    video_index: np.ndarray,
) -> dict[int, tuple[float, float]]:
    """The whole-video rule: `off_videos` judged on the observed points (as the rule's medians are), and every
    reconstructed point of those videos set in `flag` (F, P), in place. Returns `off_videos`'s result."""
    off = off_videos(options, reconstructed & observed.astype(bool), residual_px, video_index)
    for v in off:
        flag |= reconstructed & (video_index == v)[:, None]
    return off
