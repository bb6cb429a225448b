"""Videos with known poses (handheld ones the background posed frame by frame, or static ones) as the subject
path's world: one similarity, and each video's clock offset, take the subject path's cameras and trajectory into
the background's frame and scale.

The subject path solves the static cameras in a frame of its own. A posed video sees the same trajectory: at the
right similarity and clock offset, the trajectory reprojects onto its tracks. A moving camera fixes the scale with
its own baseline; a static one only with another posed video. How well the scale is fixed is measured (its
standard error, and the scales of the two halves of the observations), and a fit that does not fix it is refused.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import OptimizeResult, least_squares

from sfm.options import MAX_OFFSET_S
from sfm.subject.geometry import rodrigues
from sfm.subject.model import MIN_INLIERS, MIN_RATIO, SubjectCalibrationError, SubjectResult
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

MAX_OBSERVATIONS = 3000  # per posed video in the search and the fit (frames thinned evenly): speed
COARSE_OBSERVATIONS = 600  # per posed video in the offset search's first pass
MAX_SCALE_ERROR = 0.02  # relative: the scale's standard error or its two halves' disagreement, at most
LOST = 10  # residual, in noise scales, of an observation whose offset leaves the trajectory's time span
MIN_BASELINE = 0.02  # the posed cameras' centres must spread this fraction of their distance to the subject


@dataclass(kw_only=True)
class PosedVideo:
    """One video whose frames have known poses in the background's world, with its tracks of the subject."""

    name: str
    times: np.ndarray  # (F,) own seconds of every frame
    R: np.ndarray  # (F, 3, 3) cam_from_world, NaN where the frame has no pose
    t: np.ndarray  # (F, 3)
    xy: np.ndarray  # (F, P, 2) undistorted normalized coordinates of `points`, NaN = unseen
    focal: np.ndarray  # (F,) pixels per normalized unit: residuals in pixels
    points: list[str]  # (P,) the point names of xy's columns
    offset: float | None = None  # known clock offset (global = own + offset), None = searched
    width: int = 0  # pixels (reports only)
    height: int = 0

    @property
    def period(self) -> float:
        return float(np.median(np.diff(self.times))) if len(self.times) > 1 else 1.0 / 30

    def columns(self, points: list[str]) -> np.ndarray:
        """(F, len(points), 2): xy in the order of `points` (a trajectory's; NaN for points this video lacks)."""
        return in_order(self.xy, self.points, points)


def in_order(values: np.ndarray, names: list[str], points: list[str]) -> np.ndarray:
    """(F, len(names), 2) columns named `names` -> (F, len(points), 2) in `points`' order (NaN where absent)."""
    out = np.full((values.shape[0], len(points), 2), np.nan)
    index = {name: i for i, name in enumerate(names)}
    for j, name in enumerate(points):
        if name in index:
            out[:, j] = values[:, index[name]]
    return out


def observed(tracks: Tracks, name: str, n_frames: int, points: list[str]) -> np.ndarray:
    """(F, P, 2) pixels of one video's tracks, points in `points`' order (others dropped), NaN = unseen."""
    xy = np.full((n_frames, len(points), 2), np.nan)
    index = {p: i for i, p in enumerate(points)}
    for video, frame, point, uv in zip(tracks.video, tracks.frame, tracks.point, tracks.xy, strict=True):
        if video == name and point in index and 0 <= frame < n_frames:
            xy[frame, index[point]] = uv
    return xy


@dataclass(kw_only=True)
class PosedFit:
    name: str
    offset: float  # seconds, global = own + offset
    observations: int  # tracked frames x points compared with the trajectory
    inliers: int  # within 3 noise scales (INLIER_PX unless the path chose another)
    residual_px: float  # median reprojection error of the trajectory in the video
    runner_up_ratio: float | None  # offset search: best inliers / best further than a frame (None: offset known)
    reason: str | None = None  # why the video does not anchor the subject path (None: it does)

    def to_json(self) -> dict[str, object]:
        return {
            "name": self.name,
            "offset_s": round(self.offset, 6),
            "observations": self.observations,
            "inliers": self.inliers,
            "residual_px": round(self.residual_px, 3) if np.isfinite(self.residual_px) else None,
            "runner_up_ratio": None if self.runner_up_ratio is None else round(self.runner_up_ratio, 3),
            "reason": self.reason,
        }


@dataclass(kw_only=True)
class Alignment:
    """world = scale * Q @ subject + T."""

    scale: float
    Q: np.ndarray  # (3, 3)
    T: np.ndarray  # (3,)
    scale_error: float  # relative: the larger of the standard error and the halves' disagreement
    fits: list[PosedFit] = field(default_factory=list)
    baseline: float = 0.0  # extent of the posed frames' camera centres / their median distance to the subject

    def fit(self, name: str) -> PosedFit:
        return next(f for f in self.fits if f.name == name)

    def to_json(self) -> dict[str, object]:
        return {
            "scale": self.scale,
            "scale_error": round(self.scale_error, 6),
            "baseline": round(self.baseline, 4),
            "videos": [f.to_json() for f in self.fits],
        }

    def apply(self, result: SubjectResult) -> None:
        """Move the result's cameras and trajectory into the posed videos' world (offsets are unchanged)."""
        for camera in result.cameras:
            centre = self.scale * self.Q @ camera.centre + self.T
            camera.R = camera.R @ self.Q.T
            camera.t = -camera.R @ centre
        for name, X in result.points.items():
            result.points[name] = self.scale * X @ self.Q.T + self.T
        result.metric = True


@dataclass(kw_only=True)
class _Trajectory:
    t0: float
    h: float
    X: np.ndarray  # (T, P, 3) NaN = not triangulated

    def at(self, times: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N,) global seconds, (N,) point indices -> (N, 3) linear interpolation (NaN outside or at a gap)."""
        u = (times - self.t0) / self.h
        i = np.floor(u).astype(np.int64)
        ok = (i >= 0) & (i < len(self.X) - 1)
        ic = np.clip(i, 0, len(self.X) - 2)
        w = (u - ic)[:, None]
        out = (1 - w) * self.X[ic, points] + w * self.X[ic + 1, points]
        out[~ok] = np.nan
        return out


@dataclass(kw_only=True)
class _Rows:
    """One posed video's thinned observations."""

    own: np.ndarray  # (N,) own seconds
    point: np.ndarray  # (N,)
    x: np.ndarray  # (N, 2) normalized
    R: np.ndarray  # (N, 3, 3)
    t: np.ndarray  # (N, 3)
    focal: np.ndarray  # (N,)
    frame: np.ndarray  # (N,)


def align_to_posed(result: SubjectResult, posed: list[PosedVideo], max_offset: float = MAX_OFFSET_S) -> Alignment:
    """The similarity (and the searched clock offsets) that best reproject the subject path's trajectory onto the
    posed videos' tracks, at the noise scale `result` was solved with. Raises SubjectCalibrationError when no posed
    video agrees with the trajectory or the scale is not fixed; the message says why."""
    px = result.inlier_px
    names = list(result.points)
    if not names or len(result.times) < 2:
        raise SubjectCalibrationError("the subject path triangulated no trajectory to align with the posed videos")
    trajectory = _Trajectory(
        t0=float(result.times[0]),
        h=float(result.times[1] - result.times[0]),
        X=np.stack([result.points[n] for n in names], axis=1),
    )
    rows = [_rows(video, names) for video in posed]
    fits: list[PosedFit] = []
    starts: list[tuple[float, np.ndarray] | None] = []
    for video, mine in zip(posed, rows, strict=True):
        fit, similarity = _search(video, mine, trajectory, max_offset, px)
        fits.append(fit)
        starts.append(similarity)
    usable = [i for i, f in enumerate(fits) if f.reason is None]
    if not usable:
        raise SubjectCalibrationError(
            "no posed video's tracks agree with the subject path's trajectory: "
            + "; ".join(f"{f.name}: {f.reason}" for f in fits)
        )
    used, videos, kept = [rows[i] for i in usable], [posed[i] for i in usable], [fits[i] for i in usable]
    offsets = np.array([f.offset for f in kept])
    # started from each video's own similarity: one static video's leaves the scale free, so the best is kept
    tried = [_refine(start[1], used, videos, offsets, trajectory, px) for start in starts if start is not None]
    solution, residuals, offsets = min(tried, key=lambda t: float(t[0].cost))
    params = solution.x[:7]
    for fit, r, offset in zip(kept, used, offsets, strict=True):
        err = _reprojection_px(r, _transform(params, trajectory.at(r.own + offset, r.point)))
        finite = err[np.isfinite(err)]
        fit.offset = float(offset)
        fit.observations = len(finite)
        fit.inliers = int((finite <= 3 * px).sum())
        fit.residual_px = float(np.median(finite)) if len(finite) else float("inf")
    alignment = Alignment(
        scale=float(np.exp(params[3])),
        Q=rodrigues(params[:3]),
        T=params[4:7].copy(),
        scale_error=_scale_error(solution, residuals, used, px),
        fits=fits,
    )
    alignment.baseline = _baseline(used, kept, alignment, trajectory)
    _check(alignment, videos)
    log.info(
        "posed videos %s anchor the subject path: scale %.4g (±%.2g %%)",
        ", ".join(f.name for f in fits if f.reason is None),
        alignment.scale,
        100 * alignment.scale_error,
    )
    return alignment


def _rows(video: PosedVideo, points: list[str]) -> _Rows:
    """The video's observations on its posed frames, points numbered as in `points` (the trajectory's)."""
    xy = video.columns(points)
    posed = np.isfinite(video.R[:, 0, 0])
    seen = np.isfinite(xy[..., 0]) & posed[:, None]  # (F, P)
    stride = max(1, int(np.ceil(seen.sum() / MAX_OBSERVATIONS)))
    frames = np.flatnonzero(seen.any(1))[::stride]
    f, p = np.nonzero(seen[frames])
    f = frames[f]
    return _Rows(own=video.times[f], point=p, x=xy[f, p], R=video.R[f], t=video.t[f], focal=video.focal[f], frame=f)


def _subset(rows: _Rows, n: int) -> _Rows:
    """Every k-th row, at most `n`."""
    pick = slice(None, None, max(1, int(np.ceil(len(rows.own) / n))))
    return _Rows(
        own=rows.own[pick],
        point=rows.point[pick],
        x=rows.x[pick],
        R=rows.R[pick],
        t=rows.t[pick],
        focal=rows.focal[pick],
        frame=rows.frame[pick],
    )


def _reprojection_px(rows: _Rows, X: np.ndarray) -> np.ndarray:
    """(N,) pixels (inf behind the camera or without a trajectory sample)."""
    Xc = np.einsum("nij,nj->ni", rows.R, X) + rows.t
    with np.errstate(all="ignore"):
        uv = Xc[:, :2] / Xc[:, 2:3]
        err = np.linalg.norm(uv - rows.x, axis=1) * rows.focal
    return np.where(np.isfinite(err) & (Xc[:, 2] > 0), err, np.inf)


def _linear(rows: _Rows, X: np.ndarray, keep: np.ndarray) -> np.ndarray | None:
    """A (3, 3), T (3,) of x ~ R (A X + T) + t by linear least squares on the `keep` rows -> (12,) or None."""
    if keep.sum() < 8:
        return None
    R, t, x, Xk = rows.R[keep], rows.t[keep], rows.x[keep], X[keep]
    blocks = []
    rhs = []
    for axis in range(2):
        u = np.zeros((len(x), 3))
        u[:, axis] = 1.0
        u[:, 2] = -x[:, axis]  # u . (R (A X + T) + t) = 0
        w = np.einsum("nji,nj->ni", R, u)  # R^T u
        blocks.append(np.concatenate([(w[:, :, None] * Xk[:, None, :]).reshape(len(x), 9), w], axis=1))
        rhs.append(-np.einsum("ni,ni->n", u, t))
    M, b = np.concatenate(blocks), np.concatenate(rhs)
    return _solve(M, b)


def _solve(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least squares by the (column-scaled) normal equations: a 12 x 12 solve, far cheaper than lstsq here."""
    scale = np.linalg.norm(M, axis=0)
    scale[scale == 0] = 1.0
    Ms = M / scale
    N = Ms.T @ Ms
    N[np.diag_indices_from(N)] += 1e-12
    return np.linalg.solve(N, Ms.T @ b) / scale


def _as_similarity(params: np.ndarray, rows: _Rows, X: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The nearest similarity to the linear fit's A, with T fitted again: (7,) rvec, log scale, T."""
    A = params[:9].reshape(3, 3)
    U, S, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    Q = U @ np.diag([1.0, 1.0, d]) @ Vt
    s = float(np.mean(S))
    if not np.isfinite(s) or s <= 0:
        s = 1.0
    sol = _linear_translation(rows, s * X @ Q.T, keep)
    return np.concatenate([cv2.Rodrigues(Q)[0].ravel(), [np.log(s)], sol])


def _linear_translation(rows: _Rows, Y: np.ndarray, keep: np.ndarray) -> np.ndarray:
    R, t, x, Yk = rows.R[keep], rows.t[keep], rows.x[keep], Y[keep]
    blocks, rhs = [], []
    for axis in range(2):
        u = np.zeros((len(x), 3))
        u[:, axis] = 1.0
        u[:, 2] = -x[:, axis]
        w = np.einsum("nji,nj->ni", R, u)
        blocks.append(w)
        rhs.append(-np.einsum("ni,ni->n", u, t) - np.einsum("ni,ni->n", w, Yk))
    return _solve(np.concatenate(blocks), np.concatenate(rhs))


def _transform(params: np.ndarray, X: np.ndarray) -> np.ndarray:
    return float(np.exp(params[3])) * X @ rodrigues(params[:3]).T + params[4:7]


def _score(rows: _Rows, X: np.ndarray, px: float) -> tuple[int, np.ndarray | None]:
    """Inliers of the best similarity at one offset (trimmed linear fits), and its parameters."""
    valid = np.isfinite(X[:, 0])
    keep = valid.copy()
    params = None
    for _ in range(3):
        linear = _linear(rows, X, keep)
        if linear is None:
            return 0, None
        params = _as_similarity(linear, rows, X, keep)
        err = _reprojection_px(rows, _transform(params, X))
        err[~valid] = np.inf
        finite = err[np.isfinite(err)]
        if not len(finite):
            return 0, None
        keep = err <= max(3 * px, float(np.median(finite)))
    assert params is not None
    err = _reprojection_px(rows, _transform(params, X))
    return int((err <= 3 * px).sum()), params


def _search(
    video: PosedVideo, rows: _Rows, trajectory: _Trajectory, max_offset: float, px: float
) -> tuple[PosedFit, tuple[float, np.ndarray] | None]:
    """The video's clock offset (searched over ±max_offset a frame apart, unless known) and a similarity there."""
    period = video.period
    if video.offset is not None:
        candidates = np.array([video.offset])
    else:
        # offsets where the video's observations can meet the trajectory at all (a huge --max-offset stays cheap)
        end = trajectory.t0 + trajectory.h * (len(trajectory.X) - 1)
        low = max(-max_offset, trajectory.t0 - float(rows.own.max()))
        high = min(max_offset, end - float(rows.own.min()))
        candidates = np.arange(low, high + 0.5 * period, period) if high >= low else np.zeros(1)
    coarse = _subset(rows, COARSE_OBSERVATIONS)
    scores = np.array([_score(coarse, trajectory.at(coarse.own + o, coarse.point), px)[0] for o in candidates])
    k = int(np.argmax(scores))
    far = np.abs(candidates - candidates[k]) > 1.5 * period
    runner = int(scores[far].max()) if far.any() else 0
    ratio = None if video.offset is not None else float(scores[k] / max(runner, 1))
    near = np.flatnonzero(np.abs(candidates - candidates[k]) <= 1.5 * period)  # all observations, near the best
    full = [_score(rows, trajectory.at(rows.own + candidates[i], rows.point), px) for i in near]
    best = int(np.argmax([f[0] for f in full]))
    inliers, params = full[best]
    offset = float(candidates[near[best]])
    X = trajectory.at(rows.own + offset, rows.point)
    fit = PosedFit(
        name=video.name,
        offset=offset,
        observations=int(np.isfinite(X[:, 0]).sum()),
        inliers=inliers,
        residual_px=float("nan"),
        runner_up_ratio=ratio,
    )
    if not len(rows.own):
        fit.reason = (
            "none of its tracked frames has a pose (its tracks and its posed frames do not overlap): track the "
            "subject where the background posed it"
        )
        return fit, None
    if params is None or inliers < MIN_INLIERS:
        fit.reason = (
            f"only {inliers} of its tracked observations fit the subject path's trajectory at any clock offset "
            f"within ±{max_offset:g} s (< {MIN_INLIERS}): track the subject in it where the static videos see it too"
        )
        return fit, None
    if ratio is not None and ratio < MIN_RATIO:
        fit.reason = f"its clock offset is ambiguous (runner-up ratio {ratio:.2f} < {MIN_RATIO:g})"
        return fit, None
    return fit, (offset, params)


def _refine(
    start: np.ndarray,
    rows: list[_Rows],
    videos: list[PosedVideo],
    offsets: np.ndarray,
    trajectory: _Trajectory,
    px: float,
) -> tuple[OptimizeResult, Callable[[np.ndarray], np.ndarray], np.ndarray]:
    """Joint robust fit of the similarity and the searched offsets on every usable posed video's observations.
    Returns the solution (x: rvec, log scale, T, searched offsets), its residual function and every offset."""
    searched = [i for i, v in enumerate(videos) if v.offset is None]

    def unpack(x: np.ndarray) -> np.ndarray:
        o = offsets.copy()
        o[searched] = x[7:]
        return o

    def residuals(x: np.ndarray) -> np.ndarray:
        out = []
        for r, offset in zip(rows, unpack(x), strict=True):
            Y = _transform(x[:7], trajectory.at(r.own + offset, r.point))
            Xc = np.einsum("nij,nj->ni", r.R, Y) + r.t
            with np.errstate(all="ignore"):
                e = (Xc[:, :2] / Xc[:, 2:3] - r.x) * r.focal[:, None]
            # an observation the offset moves off the trajectory costs like an outlier (no free way out)
            out.append(np.where(np.isfinite(e), e, LOST * px).ravel())
        return np.concatenate(out)

    x0 = np.concatenate([start, offsets[searched]])
    solution = least_squares(residuals, x0, loss="soft_l1", f_scale=px, x_scale="jac", max_nfev=200)
    return solution, residuals, unpack(solution.x)


def _scale_error(
    solution: OptimizeResult, residuals: Callable[[np.ndarray], np.ndarray], rows: list[_Rows], px: float
) -> float:
    """The larger of the relative scale's standard error (the fit's Jacobian, robust residual spread) and the
    disagreement of the similarities fitted again on the early and the late half of each video's observations."""
    J, r, x = solution.jac, solution.fun, solution.x
    sigma2 = (1.4826 * float(np.median(np.abs(r[r != 0])))) ** 2 if np.any(r != 0) else 0.0
    try:
        standard = float(np.sqrt(max(np.linalg.inv(J.T @ J)[3, 3] * sigma2, 0.0)))
    except np.linalg.LinAlgError:
        return float("inf")
    early = np.concatenate([np.repeat(row.own <= np.median(row.own), 2) for row in rows if len(row.own)])
    halves = []
    for half in (early, ~early):
        if half.sum() < 2 * MIN_INLIERS:
            return float("inf")

        def one(y: np.ndarray, half: np.ndarray = half) -> np.ndarray:
            return residuals(np.concatenate([y, x[7:]]))[half]  # the offsets held

        halves.append(float(least_squares(one, x[:7], loss="soft_l1", f_scale=px, x_scale="jac").x[3]))
    return max(standard, abs(halves[0] - halves[1]))


def _baseline(rows: list[_Rows], fits: list[PosedFit], alignment: Alignment, trajectory: _Trajectory) -> float:
    """Extent of the posed frames' camera centres (along their main direction) over their median distance to the
    aligned trajectory: the scale is seen only through the posed cameras' own baseline (one static camera has none)."""
    centres, distances = [], []
    for r, fit in zip(rows, fits, strict=True):
        X = trajectory.at(r.own + fit.offset, r.point)
        ok = np.isfinite(X[:, 0])
        c = -np.einsum("nji,nj->ni", r.R[ok], r.t[ok])  # (N, 3) centres
        Y = alignment.scale * X[ok] @ alignment.Q.T + alignment.T
        centres.append(c)
        distances.append(np.linalg.norm(Y - c, axis=1))
    c = np.concatenate(centres)
    d = np.concatenate(distances)
    if not len(d):
        return 0.0
    centred = c - c.mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]  # the centres' main direction
    along = centred @ axis
    return float(along.max() - along.min()) / max(float(np.median(d)), 1e-12)


def _check(alignment: Alignment, videos: list[PosedVideo]) -> None:
    """The scale is fixed (the residuals are judged after the joint adjustment: `sfm.subject.posed_bundle`)."""
    names = ", ".join(v.name for v in videos)
    if alignment.baseline < MIN_BASELINE:
        raise SubjectCalibrationError(
            f"the posed videos ({names}) do not fix the subject path's scale: their cameras move "
            f"{100 * alignment.baseline:.1f} % of their distance to the subject (< {100 * MIN_BASELINE:g} %)"
        )
    if not np.isfinite(alignment.scale_error) or alignment.scale_error > MAX_SCALE_ERROR:
        raise SubjectCalibrationError(
            f"the posed videos ({names}) do not fix the subject path's scale (uncertain by "
            f"{100 * alignment.scale_error:.1f} % > {100 * MAX_SCALE_ERROR:g} %)"
        )
