"""Video clocks: map every video's own time (decoder time, or frame / fps) to one global time.

Each video v gets g = offset_v + rate_v * own + drift_v * own^2 (seconds); the reference video (the first one with
decoder times) fixes the gauge: offset 0, rate 1, drift 0. Two sources of evidence:

* Links of W (this module). Column f of W says S_f ~ sum_j W_jf S_j with every j in another video; locally the
  motion is smooth, so frame f's global time is close to the same combination of its neighbours' times:
  g(f) - sum_j W_jf g(j) ~ 0. That is linear in the clock parameters. A robust start (per pair of videos, a RANSAC
  line through the (own time, neighbours' own time) links, chained along a maximum spanning tree from the reference)
  then IRLS with a Cauchy loss on the link residuals; the covariance comes from the final weighted normal equations.
* The 2D tracks and poses (`reconstruct.clocks.search`): the offsets and rates that make the interpolated tracks of
  different videos triangulate. Needed where W is ambiguous (one point seen from far away: almost any two rays of
  different videos pass close to each other, so the solver's shapes, and W, do not know the time).

`estimate_clocks` fits the links, runs the track search (by default always: it is cheap, and the links of a solver's
W were measured 0.7 frame periods off on simulated phones) and keeps the estimate the evidence supports (see its
docstring). Each frame's time std holds the clock's covariance, the capture-time jitter around the clock (from the
tracks, else the links) and a floor of 1/20 frame period. The result goes into sequencing.json under the key
`clocks` (`Clocks.to_json`, docs/formats.md).
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import minimum_spanning_tree

from dynrecon.errors import InputError
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0  # own time of a video without decoder times or a known frame rate (its rate absorbs the error)
CAUCHY_C = 2.385  # Cauchy loss constant: 95 % efficiency under Gaussian noise
MAD_TO_SIGMA = 1.4826


class ClockModel(enum.Enum):
    OFFSET = "offset"  # rate fixed to 1 (decoder times assumed exact)
    AFFINE = "affine"  # offset and rate
    DRIFT = "drift"  # offset, rate and a quadratic drift


class SearchMode(enum.Enum):
    AUTO = "auto"  # run the track search when the links are weak or the problem has few points
    ALWAYS = "always"
    NEVER = "never"


class TimeSource(enum.Enum):
    DECODER = "decoder"  # decoder timestamps of cameras.json
    FPS = "fps"  # frame / fps with a known frame rate
    NOMINAL = "nominal"  # frame / DEFAULT_FPS: the rate of this video carries its unknown frame rate


@dataclass(kw_only=True)
class ClockOptions:
    model: ClockModel = ClockModel.AFFINE
    # ALWAYS by default: the search costs ~1 s CPU (F = 500, P = 41; F = 1800, P = 1) and W's links alone were
    # 0.7 frame periods off (median) on a simulated phone capture where the tracks were within 0.1.
    search: SearchMode = SearchMode.ALWAYS
    fps: dict[str, float] = field(default_factory=dict)  # frame rate of videos without decoder times
    reference: str | None = None  # gauge video; default: the first video with decoder times
    min_weight: float = 1e-6  # W entries below this are numerical dust, not links (dropping real ones biases)
    min_links: int = 10  # inlier links a video needs (to the already-clocked videos) to be identified by W
    ransac_iterations: int = 300
    ransac_threshold_periods: float = 1.0  # link inlier threshold in frame periods of the linked video
    irls_iterations: int = 30
    # AUTO: the search runs when the problem has at most this many reconstructable points ...
    search_max_points: int = 3
    # ... or when fewer than this share of the links are inliers, or a video is not identified by W.
    min_inlier_share: float = 0.6
    # Links and tracks agree when their offsets differ by less than this many combined standard deviations
    # (or less than `agree_periods` frame periods): then both are fused.
    agree_sigmas: float = 4.0
    agree_periods: float = 0.5
    # Each frame's time std is at least this share of its video's frame period: interpolating a curved track
    # linearly between frames (and expressing a shape by neighbours) leaves a sub-frame bias the covariance does
    # not see (measured on synthetic flights: 0.5-1 ms at 30-60 fps).
    std_floor_periods: float = 0.05
    seed: int = 0


@dataclass(kw_only=True)
class VideoClock:
    """Clock of one video: global = offset + rate * own + drift * own^2 (s); stds are 1-sigma, 0 when fixed."""

    name: str
    time_source: TimeSource
    offset: float = math.nan
    rate: float = math.nan
    drift: float = 0.0
    offset_std: float = math.nan
    rate_std: float = math.nan
    drift_std: float = 0.0
    method: str = "unidentified"  # reference | links | tracks | combined | unidentified
    identified: bool = False
    links: int = 0  # inlier W links touching this video
    track_residual_px: float = math.nan  # robust RMS triangulation residual of its tracks (track search)
    frame_scatter: float = math.nan  # s, per-frame timing spread around the clock (jitter or floor), in time_std


@dataclass(kw_only=True)
class Clocks:
    model: ClockModel
    reference: str
    videos: list[VideoClock]
    frame_videos: list[str]  # (F,)
    frames: np.ndarray  # (F,) frame numbers
    own_time: np.ndarray  # (F,) s
    global_time: np.ndarray  # (F,) s, NaN for frames of unidentified videos
    global_std: np.ndarray  # (F,) s
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)

    def video(self, name: str) -> VideoClock:
        for clock in self.videos:
            if clock.name == name:
                return clock
        raise KeyError(name)

    def to_json(self) -> dict[str, Any]:
        """The `clocks` value of sequencing.json (JSON types only; NaN -> null)."""
        return {
            "model": self.model.value,
            "unit": "s",
            "reference": self.reference,
            "videos": [{
                "video": c.name, "time_source": c.time_source.value, "method": c.method,
                "identified": c.identified, "offset": _num(c.offset), "offset_std": _num(c.offset_std),
                "rate": _num(c.rate), "rate_std": _num(c.rate_std), "drift": _num(c.drift),
                "drift_std": _num(c.drift_std), "links": int(c.links), "track_residual_px": _num(c.track_residual_px),
                "frame_scatter": _num(c.frame_scatter),
            } for c in self.videos],
            "frames": [{"video": v, "frame": int(f), "own_time": _num(o), "time": _num(g), "time_std": _num(s)}
                       for v, f, o, g, s in zip(self.frame_videos, self.frames, self.own_time, self.global_time,
                                                self.global_std, strict=True)],
            "warnings": list(self.warnings),
            "diagnostics": _plain(self.diagnostics),
        }

    @classmethod
    def from_json(cls, document: Any, path: str | Path | None = None) -> Clocks:
        """Inverse of `to_json`; malformed input raises InputError naming `path`."""
        try:
            videos = [VideoClock(
                name=str(v["video"]), time_source=TimeSource(v["time_source"]), method=str(v["method"]),
                identified=bool(v["identified"]), offset=_float(v["offset"]), offset_std=_float(v["offset_std"]),
                rate=_float(v["rate"]), rate_std=_float(v["rate_std"]), drift=_float(v["drift"]),
                drift_std=_float(v["drift_std"]), links=int(v.get("links", 0)),
                track_residual_px=_float(v.get("track_residual_px")),
                frame_scatter=_float(v.get("frame_scatter")),
            ) for v in document["videos"]]
            entries = document["frames"]
            return cls(
                model=ClockModel(document["model"]), reference=str(document["reference"]), videos=videos,
                frame_videos=[str(e["video"]) for e in entries],
                frames=np.array([int(e["frame"]) for e in entries], dtype=np.int64),
                own_time=np.array([_float(e["own_time"]) for e in entries]),
                global_time=np.array([_float(e["time"]) for e in entries]),
                global_std=np.array([_float(e["time_std"]) for e in entries]),
                warnings=[str(w) for w in document.get("warnings", [])],
                diagnostics=dict(document.get("diagnostics", {})),
            )
        except (KeyError, TypeError, ValueError, OverflowError, RecursionError) as error:
            raise InputError(path, f"invalid 'clocks' entry: {repr(error)[:200]}",
                             fix="rewrite it with `dynrecon solve`, or remove the key") from None


def _num(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _float(value: Any) -> float:
    return math.nan if value is None else float(value)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# ---------------------------------------------------------------------------------------------------------------
# Own time


def own_times(problem: Problem, fps: Mapping[str, float] | None = None) -> tuple[np.ndarray, list[TimeSource]]:
    """(F,) own time of every frame in s, and the source per video.

    Decoder times where given; a frame missing its time in a video that has times elsewhere is placed on the line
    time ~ frame fitted to that video's times (registration may drop frames, decoders do not skip timestamps).
    """
    fps = fps or {}
    own = np.full(problem.num_frames, np.nan)
    sources: list[TimeSource] = []
    for v, name in enumerate(problem.video_names):
        rows = np.flatnonzero(problem.video_index == v)
        frames = problem.frames[rows].astype(float)
        times = problem.times[rows]
        known = np.isfinite(times)
        if known.sum() >= 2 and np.ptp(frames[known]) > 0:
            slope, intercept = np.polyfit(frames[known], times[known], 1)
            own[rows] = np.where(known, times, intercept + slope * frames)
            sources.append(TimeSource.DECODER)
        elif name in fps and fps[name] > 0:
            own[rows] = frames / fps[name]
            sources.append(TimeSource.FPS)
        else:
            own[rows] = frames / DEFAULT_FPS
            sources.append(TimeSource.NOMINAL)
    return own, sources


def frame_periods(own: np.ndarray, video_index: np.ndarray, num_videos: int) -> np.ndarray:
    """(N,) median interval between consecutive frames of each video, s."""
    periods = np.full(num_videos, np.nan)
    for v in range(num_videos):
        t = np.sort(own[video_index == v])
        steps = np.diff(t)
        steps = steps[steps > 0]
        if len(steps):
            periods[v] = float(np.median(steps))
    return periods


# ---------------------------------------------------------------------------------------------------------------
# Clock parameters as a linear model


@dataclass(kw_only=True)
class ClockParams:
    """Per video g = a + b s + c s^2 with s = own - center (centred for conditioning); cov over (a, b, c)."""

    center: np.ndarray  # (N,)
    coef: np.ndarray  # (N, 3)
    cov: np.ndarray  # (N, 3, 3), NaN for unidentified videos
    identified: np.ndarray  # (N,) bool

    def times(self, own: np.ndarray, video_index: np.ndarray) -> np.ndarray:
        s = own - self.center[video_index]
        c = self.coef[video_index]
        return c[:, 0] + c[:, 1] * s + c[:, 2] * s * s

    def time_std(self, own: np.ndarray, video_index: np.ndarray) -> np.ndarray:
        s = own - self.center[video_index]
        basis = np.stack([np.ones_like(s), s, s * s], axis=1)
        var = np.einsum("fi,fij,fj->f", basis, self.cov[video_index], basis)
        return np.sqrt(np.maximum(var, 0.0))

    def offset_rate_drift(self, v: int) -> tuple[np.ndarray, np.ndarray]:
        """(offset, rate, drift) at own time 0 and their stds."""
        m = self.center[v]
        T = np.array([[1.0, -m, m * m], [0.0, 1.0, -2.0 * m], [0.0, 0.0, 1.0]])
        values = T @ self.coef[v]
        cov = T @ self.cov[v] @ T.T
        return values, np.sqrt(np.maximum(np.diag(cov), 0.0))


def free_terms(model: ClockModel) -> int:
    return {ClockModel.OFFSET: 1, ClockModel.AFFINE: 2, ClockModel.DRIFT: 3}[model]


def reference_coef(center: float) -> np.ndarray:
    """g = own for the reference video: a = center, b = 1, c = 0."""
    return np.array([center, 1.0, 0.0])


def cluster_covariance(J: np.ndarray, r: np.ndarray, weights: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Cluster-robust (sandwich) covariance of a weighted least-squares estimate: H^-1 M H^-1 with H = J^T W J and
    M = sum over clusters of (J_c^T W_c r_c)(J_c^T W_c r_c)^T, times n / (n - p).

    Residuals of neighbouring frames share interpolation errors and neighbours, so the plain sigma^2 H^-1 is too
    optimistic (measured: ~30 % of errors within 2 std); clusters of ~0.5 s absorb that correlation.
    """
    n, p = J.shape
    cov = np.full((p, p), np.inf)
    if n <= p:
        return cov
    H = J.T @ (weights[:, None] * J)
    scores = J * (weights * r)[:, None]  # (n, p)
    _, cluster_index = np.unique(clusters, return_inverse=True)
    summed = np.zeros((int(cluster_index.max()) + 1, p))
    np.add.at(summed, cluster_index, scores)
    M = summed.T @ summed
    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return cov
    return (H_inv @ M @ H_inv) * n / (n - p)


# ---------------------------------------------------------------------------------------------------------------
# Links of W


@dataclass(kw_only=True)
class Links:
    """Sparse link equations: frame[i] is combined from (neighbour, weight) entries of rows ptr[i]:ptr[i+1]."""

    frame: np.ndarray  # (L,) frames with at least one link
    neighbour: np.ndarray  # (E,) frame index of each entry
    weight: np.ndarray  # (E,) normalized per frame to sum to 1
    row: np.ndarray  # (E,) link index of each entry


def w_links(W: sp.spmatrix, video_index: np.ndarray, min_weight: float) -> Links:
    """One link per frame whose column of W has weight >= min_weight on other videos (weights renormalized)."""
    csc = sp.csc_matrix(W)
    csc.eliminate_zeros()
    cols = np.repeat(np.arange(csc.shape[1]), np.diff(csc.indptr))
    rows, vals = csc.indices.astype(np.int64), csc.data
    keep = (vals >= min_weight) & (video_index[rows] != video_index[cols])
    rows, cols, vals = rows[keep], cols[keep], vals[keep]
    totals = np.bincount(cols, weights=vals, minlength=csc.shape[1])
    frames = np.flatnonzero(totals > 0)
    link_of = np.full(csc.shape[1], -1)
    link_of[frames] = np.arange(len(frames))
    return Links(frame=frames, neighbour=rows, weight=vals / totals[cols], row=link_of[cols])


def link_residuals(links: Links, g: np.ndarray) -> np.ndarray:
    """(L,) g(f) - sum_j w_jf g(j), s."""
    mixed = np.bincount(links.row, weights=links.weight * g[links.neighbour], minlength=len(links.frame))
    return g[links.frame] - mixed


def _pair_relations(links: Links, own: np.ndarray, video_index: np.ndarray, periods: np.ndarray, num_videos: int,
                    options: ClockOptions) -> dict[tuple[int, int], tuple[float, float, int]]:
    """Robust affine relation own_u ~ alpha + beta own_v for each pair (v, u) linked by W: (alpha, beta, inliers).

    For each link of a frame f of v, the neighbours in video u give one sample (own_f, weighted mean own time of
    u-neighbours). RANSAC on two-sample lines (or the median difference when the rate is fixed), then least squares
    on the inliers.
    """
    rng = np.random.default_rng(options.seed)
    u_entry = video_index[links.neighbour]
    key = (links.row * num_videos + u_entry).astype(np.int64)
    unique, inverse = np.unique(key, return_inverse=True)
    weight_sum = np.bincount(inverse, weights=links.weight)
    mean_own = np.bincount(inverse, weights=links.weight * own[links.neighbour]) / weight_sum
    sample_frame = links.frame[unique // num_videos]
    sample_u = (unique % num_videos).astype(np.int64)
    sample_v = video_index[sample_frame]
    relations: dict[tuple[int, int], tuple[float, float, int]] = {}
    fixed_rate = options.model is ClockModel.OFFSET
    for v in range(num_videos):
        for u in range(num_videos):
            sel = (sample_v == v) & (sample_u == u)
            n = int(sel.sum())
            if u == v or n < 2:
                continue
            x, y = own[sample_frame[sel]], mean_own[sel]
            threshold = options.ransac_threshold_periods * float(np.nanmax([periods[u], periods[v]]))
            if fixed_rate:
                alpha, beta = float(np.median(y - x)), 1.0
            else:
                i = rng.integers(0, n, size=(options.ransac_iterations, 2))
                dx = x[i[:, 1]] - x[i[:, 0]]
                ok = np.abs(dx) > 1e-9
                if not ok.any():
                    continue
                betas = (y[i[ok, 1]] - y[i[ok, 0]]) / dx[ok]
                alphas = y[i[ok, 0]] - betas * x[i[ok, 0]]
                plausible = (betas > 0.2) & (betas < 5.0)  # frame rates differ by at most 5x
                if not plausible.any():
                    continue
                alphas, betas = alphas[plausible], betas[plausible]
                counts = (np.abs(y[None] - alphas[:, None] - betas[:, None] * x[None]) < threshold).sum(axis=1)
                best = int(np.argmax(counts))
                alpha, beta = float(alphas[best]), float(betas[best])
            for _ in range(3):
                inl = np.abs(y - alpha - beta * x) < threshold
                if inl.sum() < 2:
                    break
                if fixed_rate:
                    alpha = float(np.mean(y[inl] - x[inl]))
                elif np.ptp(x[inl]) > 0:
                    beta, alpha = (float(c) for c in np.polyfit(x[inl], y[inl], 1))
            inliers = int((np.abs(y - alpha - beta * x) < threshold).sum())
            relations[(v, u)] = (alpha, beta, inliers)
    return relations


def chain_clocks(strength: np.ndarray, ref: int, centers: np.ndarray,
                 relation: Callable[[int, int], tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Clock coefficients (N, 3) and `reached` (N,) by composing pair relations along a maximum spanning tree of
    `strength` (N, N symmetric, 0 = no relation) from the reference. `relation(v, u)` gives (alpha, beta) with
    own_u = alpha + beta own_v. Shared by the link fit and the track search."""
    num_videos = len(strength)
    coef = np.full((num_videos, 3), np.nan)
    coef[ref] = reference_coef(centers[ref])
    reached = np.zeros(num_videos, dtype=bool)
    reached[ref] = True
    if num_videos < 2 or not strength.any():
        return coef, reached
    tree = minimum_spanning_tree(sp.csr_matrix(np.where(strength > 0, 1.0 / (1.0 + strength), 0.0)))
    tree = (tree + tree.T).tocsr()
    queue = [ref]
    while queue:
        v = queue.pop()
        for u in tree.indices[tree.indptr[v]:tree.indptr[v + 1]]:
            if reached[u]:
                continue
            alpha, beta = relation(v, int(u))
            # g_u(own_u) = g_v(own_v) with own_v = (own_u - alpha) / beta; g_v linear: offset o_v + rate r_v own
            o_v = coef[v, 0] - coef[v, 1] * centers[v]
            r_v = coef[v, 1]
            o_u, r_u = o_v - r_v * alpha / beta, r_v / beta
            coef[u] = [o_u + r_u * centers[u], r_u, 0.0]
            reached[u] = True
            queue.append(int(u))
    return coef, reached


def _chain_start(relations: dict[tuple[int, int], tuple[float, float, int]], ref: int, num_videos: int,
                 centers: np.ndarray, min_links: int) -> tuple[np.ndarray, np.ndarray]:
    """Start coefficients by composing pair relations along a maximum spanning tree (most inliers) from `ref`."""
    strength = np.zeros((num_videos, num_videos))
    for (v, u), (_, _, n) in relations.items():
        strength[v, u] += n
        strength[u, v] += n
    strength[strength < min_links] = 0

    def relation(v: int, u: int) -> tuple[float, float]:
        # own_u = alpha + beta own_v (from v's links) or own_v = alpha' + beta' own_u (from u's links)
        if (v, u) in relations and (u, v) in relations:
            pick = (v, u) if relations[(v, u)][2] >= relations[(u, v)][2] else (u, v)
        else:
            pick = (v, u) if (v, u) in relations else (u, v)
        alpha, beta, _ = relations[pick]
        return (alpha, beta) if pick == (v, u) else (-alpha / beta, 1.0 / beta)

    return chain_clocks(strength, ref, centers, relation)


@dataclass(kw_only=True)
class LinkFit:
    params: ClockParams
    scale: float  # robust scale of the link residuals, s
    inlier_share: float  # share of links with Cauchy weight > 0.5
    links_per_video: np.ndarray  # (N,) inlier links touching each video
    residuals: np.ndarray  # (L,) s
    frame_scatter: np.ndarray  # (N,) s, per-frame timing spread of each video's inlier links (jitter + W noise)
    warnings: list[str]


def fit_links(W: sp.spmatrix, own: np.ndarray, video_index: np.ndarray, num_videos: int, ref: int,
              options: ClockOptions, names: list[str] | None = None) -> LinkFit:
    """Robust affine (or offset / drift) clocks from the links of W; see the module docstring."""
    names = names or [f"video {v}" for v in range(num_videos)]
    periods = frame_periods(own, video_index, num_videos)
    centers = np.array([np.mean(own[video_index == v]) if np.any(video_index == v) else 0.0
                        for v in range(num_videos)])
    links = w_links(W, video_index, options.min_weight)
    warnings: list[str] = []
    nan_params = ClockParams(center=centers, coef=np.full((num_videos, 3), np.nan),
                             cov=np.full((num_videos, 3, 3), np.nan), identified=np.zeros(num_videos, dtype=bool))
    nan_params.coef[ref] = reference_coef(centers[ref])
    nan_params.cov[ref] = 0.0
    nan_params.identified[ref] = True
    if len(links.frame) == 0:
        return LinkFit(params=nan_params, scale=math.nan, inlier_share=0.0,
                       links_per_video=np.zeros(num_videos, dtype=np.int64), residuals=np.zeros(0),
                       frame_scatter=np.full(num_videos, np.nan),
                       warnings=["W has no links between videos: no clock can be estimated from it"])
    relations = _pair_relations(links, own, video_index, periods, num_videos, options)
    coef, reached = _chain_start(relations, ref, num_videos, centers, options.min_links)

    k = free_terms(options.model)
    free_videos = [v for v in range(num_videos) if reached[v] and v != ref]
    # Links among reached videos only; entries of unreached videos would be unknowns without a start.
    use_entry = reached[video_index[links.neighbour]]
    use_link = np.bincount(links.row, weights=(~use_entry).astype(float), minlength=len(links.frame)) == 0
    use_link &= reached[video_index[links.frame]]
    # Design: for frame f (row L) coefficient +phi(s_f) on video(f) block, -w phi(s_j) on video(j) blocks.
    column_of = np.full((num_videos, 3), -1)
    for i, v in enumerate(free_videos):
        column_of[v, :k] = np.arange(i * k, (i + 1) * k)
    s = own - centers[video_index]
    basis = np.stack([np.ones_like(s), s, s * s], axis=1)  # (F, 3)
    n_links = len(links.frame)
    rows_l = np.concatenate([np.arange(n_links), links.row])
    frames_l = np.concatenate([links.frame, links.neighbour])
    signs = np.concatenate([np.ones(n_links), -links.weight])
    entry_rows = np.repeat(rows_l, 3)
    entry_terms = np.tile(np.arange(3), len(rows_l))
    entry_frames = np.repeat(frames_l, 3)
    entry_values = np.repeat(signs, 3) * basis[entry_frames, entry_terms]
    entry_cols = column_of[video_index[entry_frames], entry_terms]
    is_free = entry_cols >= 0
    n_free = k * len(free_videos)
    A = sp.csr_matrix((entry_values[is_free], (entry_rows[is_free], entry_cols[is_free])), shape=(n_links, n_free))
    # Fixed parts: the reference video's coefficients and the fixed rate/drift terms of free videos.
    fixed_coef = np.zeros((num_videos, 3))
    fixed_coef[ref] = coef[ref]
    for v in free_videos:
        fixed_coef[v] = [0.0, 1.0, 0.0]  # only the terms the model does not free are read: rate 1, no drift
    fixed_values = entry_values * fixed_coef[video_index[entry_frames], entry_terms]
    fixed_values[is_free] = 0.0
    y = -np.bincount(entry_rows, weights=fixed_values, minlength=n_links)

    theta = np.concatenate([coef[v, :k] for v in free_videos]) if free_videos else np.zeros(0)
    residual = A @ theta - y
    floor = 1e-3 * float(np.nanmin(periods)) if np.isfinite(periods).any() else 1e-6
    weights = np.where(use_link, 1.0, 0.0)
    scale = floor
    cov_free = np.zeros((n_free, n_free))
    for _ in range(max(1, options.irls_iterations)):
        r_used = residual[use_link]
        scale = max(MAD_TO_SIGMA * float(np.median(np.abs(r_used))) if len(r_used) else floor, floor)
        weights = np.where(use_link, 1.0 / (1.0 + (residual / (CAUCHY_C * scale)) ** 2), 0.0)
        if n_free == 0:
            break
        Aw = A.multiply(weights[:, None]).tocsr()
        normal = (A.T @ Aw).toarray()
        rhs = Aw.T @ y
        try:
            new_theta = np.linalg.solve(normal + 1e-12 * np.eye(n_free) * np.trace(normal) / n_free, rhs)
        except np.linalg.LinAlgError:
            break
        change = float(np.max(np.abs(new_theta - theta)))
        theta = new_theta
        residual = A @ theta - y
        if change < 1e-4 * floor:
            break
    inlier = weights > 0.5
    if n_free:
        Aw = A.multiply(weights[:, None]).tocsr()
        normal = (A.T @ Aw).toarray()
        dof = max(int(inlier.sum()) - n_free, 1)
        sigma2 = float(np.sum(weights * residual ** 2)) / dof
        try:
            cov_free = sigma2 * np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            cov_free = np.full((n_free, n_free), np.inf)

    # Inlier links per video (as the expressed frame or as a neighbour).
    touching = np.zeros(num_videos, dtype=np.int64)
    for v in range(num_videos):
        involved = video_index[links.frame] == v
        involved |= np.bincount(links.row, weights=(video_index[links.neighbour] == v).astype(float),
                                minlength=n_links) > 0
        touching[v] = int(np.sum(involved & inlier))

    params = ClockParams(center=centers, coef=np.full((num_videos, 3), np.nan),
                         cov=np.full((num_videos, 3, 3), np.nan), identified=np.zeros(num_videos, dtype=bool))
    params.coef[ref] = coef[ref]
    params.cov[ref] = 0.0
    params.identified[ref] = True
    for i, v in enumerate(free_videos):
        c = fixed_coef[v].copy()
        c[:k] = theta[i * k:(i + 1) * k]
        block = cov_free[i * k:(i + 1) * k, i * k:(i + 1) * k]
        cv = np.zeros((3, 3))
        cv[:k, :k] = block
        ok = touching[v] >= options.min_links and np.all(np.isfinite(block)) and c[1] > 0
        params.coef[v] = c
        params.cov[v] = cv
        params.identified[v] = bool(ok)
        if not ok:
            warnings.append(f"video {names[v]!r}: only {touching[v]} consistent W link(s) to other videos "
                            f"(needs {options.min_links}): its clock is not identified by the sequencing")
    for v in range(num_videos):
        if not reached[v]:
            warnings.append(f"video {names[v]!r}: W does not link it to the reference video {names[ref]!r} "
                            f"with {options.min_links}+ consistent links: its clock is not identified by the "
                            "sequencing")
    used = use_link.sum()
    share = float(inlier.sum() / used) if used else 0.0
    # residual = jitter_f - sum_j w_j jitter_j: variance (1 + sum w^2) times one frame's.
    sum_w2 = np.bincount(links.row, weights=links.weight ** 2, minlength=n_links)
    scatter = np.full(num_videos, np.nan)
    for v in range(num_videos):
        sel = inlier & (video_index[links.frame] == v)
        if sel.sum() >= 3:
            scatter[v] = MAD_TO_SIGMA * float(np.median(np.abs(residual[sel]))) / math.sqrt(
                1.0 + float(np.mean(sum_w2[sel])))
    return LinkFit(params=params, scale=scale, inlier_share=share, links_per_video=touching, residuals=residual,
                   frame_scatter=scatter, warnings=warnings)


# ---------------------------------------------------------------------------------------------------------------
# Entry point


def choose_reference(problem: Problem, sources: list[TimeSource], requested: str | None) -> int:
    if requested is not None:
        if requested not in problem.video_names:
            raise InputError(None, f"clock reference video {requested!r} is not one of the solved videos",
                             fix=f"choose one of: {', '.join(problem.video_names)}")
        return problem.video_names.index(requested)
    for v, source in enumerate(sources):
        if source is TimeSource.DECODER:
            return v
    return 0


def estimate_clocks(problem: Problem, result: SolveResult, options: ClockOptions | None = None) -> Clocks:
    """Every video's clock from W's links and the tracks (see the module docstring).

    The link fit always runs. The track search runs with SearchMode.ALWAYS (the default), or with AUTO when the
    links are weak (a video unidentified, fewer than `min_inlier_share` inliers) or the problem has at most
    `search_max_points` points. Where both clock a video: links whose robust scale is within a quarter of the
    fastest frame period are fused with the tracks (inverse covariance) when they agree (middle times within
    `agree_sigmas` combined stds or `agree_periods` frame periods), else the tracks win with a warning (the
    triangulation residual is a direct measurement, W is the solver's interpretation of it); noisier links only
    clock the videos the tracks cannot. A video neither source clocks is `identified = False` with NaN times and a
    warning.
    """
    from reconstruct.clocks.search import SearchOptions, search_clocks  # the search imports this module

    options = options or ClockOptions()
    own, sources = own_times(problem, options.fps)
    N = len(problem.video_names)
    ref = choose_reference(problem, sources, options.reference)
    for v, source in enumerate(sources):
        if source is TimeSource.NOMINAL:
            log.warning("video %r has neither decoder times nor a known frame rate: own time = frame / %g s, its "
                        "rate absorbs the true frame rate", problem.video_names[v], DEFAULT_FPS)
    model = options.model
    if model is ClockModel.OFFSET and any(s is not TimeSource.DECODER for s in sources):
        log.warning("clock model 'offset' needs decoder times for every video; using 'affine'")
        model = ClockModel.AFFINE
    fit_options = ClockOptions(**{**options.__dict__, "model": model})
    link_fit = fit_links(result.W.to_csc(), own, problem.video_index, N, ref, fit_options, problem.video_names)
    periods = frame_periods(own, problem.video_index, N)
    P = int(np.sum(result.reconstructable))
    weak = (not link_fit.params.identified.all()) or link_fit.inlier_share < options.min_inlier_share
    run_search = options.search is SearchMode.ALWAYS or (
        options.search is SearchMode.AUTO and (weak or options.search_max_points >= P))
    warnings = list(link_fit.warnings)
    diagnostics: dict[str, Any] = {
        "link_scale_s": link_fit.scale, "link_inlier_share": link_fit.inlier_share,
        "links": len(link_fit.residuals), "search": run_search,
    }
    params = link_fit.params
    methods = ["links" if params.identified[v] else "unidentified" for v in range(N)]
    methods[ref] = "reference"
    track_rms = np.full(N, np.nan)
    scatter = link_fit.frame_scatter.copy()
    if run_search:
        search = search_clocks(problem, own, ref, SearchOptions(model=model, seed=options.seed, time_source=sources),
                               start=link_fit.params)
        warnings.extend(search.warnings)
        diagnostics["track_residual_px"] = search.residual_px
        track_rms = search.video_residual_px
        # Links as precise as a quarter of the fastest frame period may refine the tracks' clocks; noisier ones
        # (the solver's W on noisy or distant data) only fill in videos the tracks cannot clock.
        precise = bool(link_fit.scale <= 0.25 * float(np.nanmin(periods)))
        params, methods, fuse_notes = _combine(link_fit.params, search.params, periods, ref, options,
                                               problem.video_names, precise)
        diagnostics["links_precise"] = precise
        warnings.extend(fuse_notes)
        # Per-video jitter estimates of the tracks are noisy (a few hundred frames, noise removed by subtraction):
        # pool them over the videos.
        spreads = search.timing_spread[np.isfinite(search.timing_spread)]
        pooled = float(np.median(spreads)) if len(spreads) else math.nan
        for v in range(N):
            # The links' spread holds W's own noise too (measured 16 ms on phones whose jitter was 2 ms): the
            # tracks' estimate is the direct one wherever they clock the video.
            if methods[v] != "links" and math.isfinite(pooled):
                scatter[v] = pooled
    global_time = params.times(own, problem.video_index)
    # Per frame: the clock's own uncertainty, the frames' timing spread around it (jitter, from the links) and a
    # floor for the sub-frame bias of interpolating tracks / combining neighbours linearly.
    floor = options.std_floor_periods * periods
    frame_sd = np.fmax(np.nan_to_num(scatter, nan=0.0), floor)
    scatter = frame_sd
    global_std = np.hypot(params.time_std(own, problem.video_index), frame_sd[problem.video_index])
    videos: list[VideoClock] = []
    for v, name in enumerate(problem.video_names):
        values, stds = params.offset_rate_drift(v)
        identified = bool(params.identified[v])
        if not identified:
            global_time[problem.video_index == v] = np.nan
            global_std[problem.video_index == v] = np.nan
        videos.append(VideoClock(
            name=name, time_source=sources[v], method=methods[v] if identified else "unidentified",
            identified=identified,
            offset=float(values[0]) if identified else math.nan, rate=float(values[1]) if identified else math.nan,
            drift=float(values[2]) if identified else math.nan,
            offset_std=float(stds[0]) if identified else math.nan, rate_std=float(stds[1]) if identified else math.nan,
            drift_std=float(stds[2]) if identified else math.nan,
            links=int(link_fit.links_per_video[v]), track_residual_px=float(track_rms[v]),
            frame_scatter=float(scatter[v]),
        ))
    for w in warnings:
        log.warning("clocks: %s", w)
    return Clocks(model=model, reference=problem.video_names[ref], videos=videos, frame_videos=problem.frame_videos,
                  frames=problem.frames.copy(), own_time=own, global_time=global_time, global_std=global_std,
                  warnings=warnings, diagnostics=diagnostics)


def _combine(links: ClockParams, tracks: ClockParams, periods: np.ndarray, ref: int, options: ClockOptions,
             names: list[str], links_precise: bool = True) -> tuple[ClockParams, list[str], list[str]]:
    N = len(links.center)
    out = ClockParams(center=links.center.copy(), coef=np.full((N, 3), np.nan), cov=np.full((N, 3, 3), np.nan),
                      identified=np.zeros(N, dtype=bool))
    methods = ["unidentified"] * N
    notes: list[str] = []
    for v in range(N):
        if v == ref:
            out.coef[v], out.cov[v], out.identified[v] = links.coef[v], 0.0, True
            methods[v] = "reference"
            continue
        has_l, has_t = bool(links.identified[v]), bool(tracks.identified[v])
        if has_t and not has_l:
            out.coef[v], out.cov[v], out.identified[v] = tracks.coef[v], tracks.cov[v], True
            methods[v] = "tracks"
        elif has_l and not has_t:
            out.coef[v], out.cov[v], out.identified[v] = links.coef[v], links.cov[v], True
            methods[v] = "links"
        elif has_l and has_t:
            # Both centred at the same own time: a is the clock at the video's middle.
            gap = abs(links.coef[v, 0] - tracks.coef[v, 0])
            sigma = math.sqrt(max(links.cov[v, 0, 0] + tracks.cov[v, 0, 0], 0.0))
            if not links_precise:
                out.coef[v], out.cov[v] = tracks.coef[v], tracks.cov[v]
                methods[v] = "tracks"
                if gap > options.agree_periods * periods[v]:
                    notes.append(f"video {names[v]!r}: W links put its middle {gap / periods[v]:.1f} frame periods "
                                 "from the tracks' clock: kept the tracks' clock")
            elif gap <= max(options.agree_sigmas * sigma, options.agree_periods * periods[v]):
                out.coef[v], out.cov[v] = _fuse(links.coef[v], links.cov[v], tracks.coef[v], tracks.cov[v])
                methods[v] = "combined"
            else:
                out.coef[v], out.cov[v] = tracks.coef[v], tracks.cov[v]
                methods[v] = "tracks"
                notes.append(f"video {names[v]!r}: W links put its middle at {links.coef[v, 0]:.4f} s, the tracks "
                             f"at {tracks.coef[v, 0]:.4f} s ({gap / periods[v]:.1f} frame periods apart): kept the "
                             "tracks' clock")
            out.identified[v] = True
    return out, methods, notes


def _fuse(c1: np.ndarray, v1: np.ndarray, c2: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-covariance fusion over the free terms (zero-variance terms are fixed and equal)."""
    free = (np.diag(v1) > 0) & (np.diag(v2) > 0)
    out_c, out_v = c2.copy(), v2.copy()
    if not free.any():
        return out_c, out_v
    idx = np.flatnonzero(free)
    try:
        i1 = np.linalg.inv(v1[np.ix_(idx, idx)])
        i2 = np.linalg.inv(v2[np.ix_(idx, idx)])
        cov = np.linalg.inv(i1 + i2)
    except np.linalg.LinAlgError:
        return out_c, out_v
    out_c[idx] = cov @ (i1 @ c1[idx] + i2 @ c2[idx])
    out_v[np.ix_(idx, idx)] = cov
    return out_c, out_v
