"""Per pair of videos: the time shift maximizing two-view epipolar consistency, then the pair's geometry.

Video b's tracks are interpolated at a's frame times + shift (own_b = own_a + shift, i.e. shift = o_a - o_b). The
search is coarse-to-fine: a coarse grid scored with a batched 8-point RANSAC whose threshold allows for the motion
blur of the coarse step, then fine grids around the best peaks, then a parabola through the best fine score.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from sfm.subject.geometry import bougnoux, eight_point, sampson, weighted_fit
from sfm.subject.model import INLIER_PX, MIN_DISTINCT, MIN_RATIO, MIN_SHARED
from sfm.subject.observations import VideoObs, interpolate

log = logging.getLogger(__name__)

CHUNK = 24  # shifts scored at once (bounds the (D, H, N) Sampson tensor)
DISTINCT = 0.02  # cell size (fraction of the image size) that clusters correspondences into distinct positions
FINE_STEP = 0.25  # fine offset search step, in frame periods of the faster video
FINE_CORRESPONDENCES = 1500  # at most, per robust fit of the fine grid (an even subset)
FINE_ITERATIONS = 1000  # of each robust fit of the fine grid


@dataclass(kw_only=True)
class PairFit:
    a: int
    b: int
    shift: float  # own_b = own_a + shift
    inliers: int
    shared: int
    runner_up_ratio: float
    degenerate: str | None
    xa: np.ndarray  # (M, 2) normalized inlier correspondences in a
    xb: np.ndarray  # (M, 2) ... in b
    E: np.ndarray | None  # (3, 3) essential matrix in the current normalized coordinates
    focals: tuple[float, float]  # Bougnoux estimates (NaN when unknown or K known)
    reason: str | None = None  # why the pair is unusable (None = usable)
    score: float = 0.0  # MSAC score of the model over all shared correspondences (compares shifts)
    distinct: int = 0  # distinct (coarsely clustered) positions among the inliers
    F_px: np.ndarray | None = None  # (3, 3) fundamental matrix in centred pixels of the current focals (unknown K)
    ambiguous: bool = False  # another time offset explains the tracks almost as well
    claim: str | None = None  # with declared offsets: "held", or why the tracks contradict them

    @property
    def usable(self) -> bool:
        return self.reason is None and self.degenerate is None


def pair_correspondences(
    oa: VideoObs, ob: VideoObs, shifts: np.ndarray, stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """shifts: (D,) -> xa, xb: (D, Fa / stride * P, 2) normalized with NaN (every `stride`-th frame of a)."""
    max_gap = 2.5 * ob.period  # bridge at most one missing sample
    xb = interpolate(ob.norm, ob.times, oa.times[None, ::stride] + shifts[:, None], max_gap)  # (D, Fa', P, 2)
    xa = np.broadcast_to(oa.norm[::stride], xb.shape)
    return xa.reshape(len(shifts), -1, 2), xb.reshape(len(shifts), -1, 2)


def correspondences(oa: VideoObs, ob: VideoObs, shift: float) -> tuple[np.ndarray, np.ndarray]:
    """The pair's correspondences at one shift (own_b = own_a + shift): (M, 2) normalized coordinates in a and b,
    every observation of a with b's track interpolated at that instant."""
    xa, xb = pair_correspondences(oa, ob, np.array([shift]))
    ok = np.isfinite(xa[0, :, 0]) & np.isfinite(xb[0, :, 0])
    return xa[0, ok], xb[0, ok]


def _score(
    oa: VideoObs,
    ob: VideoObs,
    shifts: np.ndarray,
    thr: float,
    hyps: int,
    n_max: int,
    essential: bool,
    min_shared: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """MSAC scores and valid-correspondence counts, (D,) each; thr in normalized units."""
    scores = np.zeros(len(shifts))
    counts = np.zeros(len(shifts), dtype=np.int64)
    for start in range(0, len(shifts), CHUNK):
        sl = slice(start, start + CHUNK)
        stride = max(1, oa.norm.shape[0] * oa.norm.shape[1] // (8 * n_max))  # enough to pick n_max from
        xa, xb = pair_correspondences(oa, ob, shifts[sl], stride)
        valid = np.isfinite(xa[..., 0]) & np.isfinite(xb[..., 0])  # (d, M)
        n_valid = valid.sum(1)
        counts[sl] = n_valid
        if n_valid.max() < max(8, min_shared):
            continue
        # a random subset of the valid correspondences of each shift, valid ones first
        key = np.where(valid, rng.random(valid.shape), 2.0)
        order = np.argsort(key, axis=1)[:, :n_max]  # (d, N)
        A = np.take_along_axis(xa, order[..., None], axis=1)
        B = np.take_along_axis(xb, order[..., None], axis=1)
        w = np.take_along_axis(valid, order, axis=1).astype(float)  # (d, N)
        A, B = np.nan_to_num(A), np.nan_to_num(B)
        n_used = np.maximum(w.sum(1), 1).astype(np.int64)
        idx = (rng.random((len(A), hyps, 8)) * n_used[:, None, None]).astype(np.int64)  # (d, H, 8)
        rows = np.arange(len(A))[:, None, None]
        F = eight_point(A[rows, idx], B[rows, idx], essential)  # (d, H, 3, 3)
        err = sampson(F, A, B)  # (d, H, N)
        s = (np.maximum(0.0, 1.0 - err / thr**2) * w[:, None, :]).sum(-1)  # (d, H)
        best_h = np.argmax(s, axis=1)
        best_s = s[np.arange(len(A)), best_h]  # (d,)
        soft = np.maximum(0.0, 1.0 - err[np.arange(len(A)), best_h] / thr**2) * w  # (d, N)
        for _ in range(2):  # local optimization: refit on the soft inliers, keep it when it scores better
            F_lo = weighted_fit(A, B, soft, essential)[:, None]  # (d, 1, 3, 3)
            e_lo = sampson(F_lo, A, B)[:, 0]  # (d, N)
            s_lo = (np.maximum(0.0, 1.0 - e_lo / thr**2) * w).sum(-1)
            better = s_lo > best_s
            best_s = np.where(better, s_lo, best_s)
            soft = np.where(better[:, None], np.maximum(0.0, 1.0 - e_lo / thr**2) * w, soft)
        best = best_s * n_valid / n_used * stride  # estimate for all valid correspondences
        scores[sl] = np.where(n_valid >= max(8, min_shared), best, 0.0)
    return scores, counts


def _image_speed(o: VideoObs) -> float:
    """Median speed of the tracked points in pixels per second, between consecutive samples of each point."""
    speeds = []
    for p in range(o.norm.shape[1]):
        seen = np.flatnonzero(np.isfinite(o.norm[:, p, 0]))
        if len(seen) < 2:
            continue
        dt = np.diff(o.times[seen])
        near = dt <= 1.5 * o.period  # samples one apart, not across a gap
        step = np.linalg.norm(np.diff(o.norm[seen, p], axis=0), axis=-1) * o.focal
        speeds.append(step[near] / dt[near])
    d = np.concatenate(speeds) if speeds else np.zeros(0)
    return float(np.median(d)) if len(d) else 0.0


def _peaks(shifts: np.ndarray, scores: np.ndarray, separation: float, count: int) -> list[float]:
    out: list[float] = []
    for i in np.argsort(-scores):
        if scores[i] <= 0 or scores[i] < 0.3 * scores.max() or len(out) >= count:
            break
        if all(abs(shifts[i] - p) > separation for p in out):
            out.append(float(shifts[i]))
    return out


def search_range(oa: VideoObs, ob: VideoObs, max_offset: float) -> tuple[float, float]:
    """The shifts a pair's search tries: within `max_offset` each way and where the two videos' times overlap."""
    return max(-max_offset, ob.times[0] - oa.times[-1]), min(max_offset, ob.times[-1] - oa.times[0])


def fit_pair(
    oa: VideoObs,
    ob: VideoObs,
    a: int,
    b: int,
    max_offset: float,
    rng: np.random.Generator,
    inlier_px: float = INLIER_PX,
) -> PairFit:
    """The pair's time shift (searched within `max_offset` seconds each way) and its geometry there;
    `inlier_px`: the tracks' noise scale (the RANSAC threshold)."""
    essential = oa.known_K and ob.known_K  # an E needs both calibrations; else an F (up to the focal guess)
    f_mean = float(np.sqrt(oa.focal * ob.focal))
    period = max(oa.period, ob.period)
    fine = FINE_STEP * min(oa.period, ob.period)
    speed = max(_image_speed(oa), _image_speed(ob))
    # a coarse step whose motion blur stays near the inlier threshold, between the fine step and 3 frames
    coarse = float(np.clip(4 * inlier_px / max(speed, 1e-9), fine, 3 * period))
    lo, hi = search_range(oa, ob, max_offset)
    empty = PairFit(
        a=a,
        b=b,
        shift=0.0,
        inliers=0,
        shared=0,
        runner_up_ratio=1.0,
        degenerate=None,
        xa=np.zeros((0, 2)),
        xb=np.zeros((0, 2)),
        E=None,
        focals=(np.nan, np.nan),
    )
    if hi < lo:
        empty.reason = "the videos never overlap in time within max_offset"
        return empty
    grid = np.arange(lo, hi + coarse / 2, coarse)
    thr_c = (inlier_px + 0.5 * coarse * speed) / f_mean
    c_scores, c_counts = _score(oa, ob, grid, thr_c, 64, 200, False, MIN_SHARED, rng)
    if c_counts.max() < MIN_SHARED:
        empty.shared = int(c_counts.max())
        empty.reason = f"at most {int(c_counts.max())} shared observations at any time offset (min_shared={MIN_SHARED})"
        return empty
    candidates: list[float] = []
    step = max(fine, 2 * coarse / 8)  # at most 9 robust fits per peak
    # peaks further apart than the ambiguity window each get a fine search (the runner-up is one of them)
    for peak in _peaks(grid, c_scores, period + coarse, 5):
        f_grid = np.arange(peak - coarse, peak + coarse + step / 2, step)
        # the fine scores come from the full robust estimator (cv2 MAGSAC): the batched 8-point is too noisy here
        f_scores = np.array(
            [
                _geometry(
                    oa, ob, a, b, s, 1.0, essential, inlier_px, n_max=FINE_CORRESPONDENCES, iterations=FINE_ITERATIONS
                ).score
                for s in f_grid
            ],
            dtype=float,
        )
        i = int(np.argmax(f_scores))
        shift = float(f_grid[i])
        if 0 < i < len(f_grid) - 1:  # sub-step parabola
            y0, y1, y2 = f_scores[i - 1 : i + 2]
            den = y0 - 2 * y1 + y2
            if den < 0:
                shift += float(np.clip(0.5 * (y0 - y2) / den, -0.5, 0.5)) * step
        candidates.append(shift)
    # the peaks compete on the full robust model's MSAC score (an E when both K are known: 5 dof discriminate best)
    # only the winner's degeneracy matters (the plane check's robust fit is not cheap)
    fits = [_geometry(oa, ob, a, b, shift, 1.0, essential, inlier_px) for shift in candidates]
    best = max(fits, key=lambda f: f.score)
    _judge(best, oa, ob, inlier_px / f_mean)
    far = [f.score for f in fits if abs(f.shift - best.shift) > period]
    if far:  # best over the best elsewhere, with the same estimator: >= 1 by construction
        best.runner_up_ratio = float(best.score / max(far)) if max(far) > 0 else float("inf")
    else:  # no other peak reached the candidate level: the coarse scores say how far behind the rest is
        near = np.abs(grid - best.shift) <= period + coarse
        c_far = float(c_scores[~near].max()) if (~near).any() else 0.0
        c_near = float(c_scores[near].max()) if near.any() else 0.0
        best.runner_up_ratio = max(1.0, c_near / c_far) if c_far > 0 else float("inf")
    # one point gives fewer constraints per frame: a single-point pair needs a clearer win
    margin = MIN_RATIO - 1.0 if oa.xy.shape[1] > 1 else 3 * (MIN_RATIO - 1.0)
    best.ambiguous = best.runner_up_ratio < 1.0 + margin
    return best


def fit_at(oa: VideoObs, ob: VideoObs, a: int, b: int, shift: float, inlier_px: float = INLIER_PX) -> PairFit:
    """The pair's model at a given shift (own_b = own_a + shift), e.g. the one the chained offsets imply."""
    fit = _geometry(oa, ob, a, b, shift, float("nan"), oa.known_K and ob.known_K, inlier_px)
    _judge(fit, oa, ob, inlier_px / float(np.sqrt(oa.focal * ob.focal)))
    return fit


def _geometry(
    oa: VideoObs,
    ob: VideoObs,
    a: int,
    b: int,
    shift: float,
    ratio: float,
    essential: bool,
    inlier_px: float,
    n_max: int = 0,
    iterations: int = 5000,
) -> PairFit:
    """The pair's model and inliers at a shift, from its correspondences (an even subset of n_max); `_judge` adds
    its degeneracy."""
    xa, xb = correspondences(oa, ob, shift)
    if n_max and len(xa) > n_max:
        keep = np.linspace(0, len(xa) - 1, n_max).astype(np.int64)
        xa, xb = xa[keep], xb[keep]
    fit = PairFit(
        a=a,
        b=b,
        shift=shift,
        inliers=0,
        shared=len(xa),
        runner_up_ratio=ratio,
        degenerate=None,
        xa=xa,
        xb=xb,
        E=None,
        focals=(np.nan, np.nan),
    )
    if len(xa) < max(8, MIN_SHARED):
        fit.reason = f"only {len(xa)} shared observations at the best time offset"
        return fit
    f_mean = float(np.sqrt(oa.focal * ob.focal))
    thr = inlier_px / f_mean
    F: np.ndarray | None = None
    E: np.ndarray | None = None
    try:
        if essential:
            E, mask = cv2.findEssentialMat(
                xa, xb, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999, threshold=thr, maxIters=iterations
            )
        else:
            # an F in centred pixels of the focal guesses (their principal points), then Bougnoux's focals
            pa, pb = xa * oa.focal, xb * ob.focal
            F, mask = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, inlier_px, 0.9999, iterations)
    except cv2.error as error:  # USAC asserts on some degenerate samples (a few positions repeated) instead
        said = str(error).strip().splitlines()
        fit.reason = f"no epipolar geometry found (OpenCV: {said[-1] if said else type(error).__name__})"
        return fit
    if not essential:
        if F is not None and F.shape == (3, 3):
            fa, fb = bougnoux(F)
            fit.focals = (fa, fb)
            E = np.diag([oa.focal, oa.focal, 1.0]) @ F.T @ np.diag([ob.focal, ob.focal, 1.0])
            E = E.T  # E = Kb^T F Ka with the current (guessed) intrinsics
        else:
            E = None
    if E is None or mask is None or E.shape != (3, 3):
        fit.reason = "no epipolar geometry found"
        return fit
    inl = mask.ravel().astype(bool)
    # MSAC over all correspondences: unlike the inlier count it keeps ranking shifts once every point is an inlier
    err = sampson(E[None], xa, xb)[0]  # (N,) squared, normalized units
    fit.score = float(np.maximum(0.0, 1.0 - err / thr**2).sum())
    fit.E, fit.inliers, fit.xa, fit.xb = E, int(inl.sum()), xa[inl], xb[inl]
    if not essential:
        fit.F_px = F
    if fit.inliers < max(8, MIN_SHARED):
        fit.reason = f"only {fit.inliers} epipolar inliers"
    return fit


def _judge(fit: PairFit, oa: VideoObs, ob: VideoObs, thr: float) -> None:
    """Set the fit's distinct positions and its degeneracy (None, or why its inliers determine no geometry)."""
    if fit.reason is not None:
        return
    size_a, size_b = _size(oa), _size(ob)
    cells = np.hstack(
        [np.floor(fit.xa * oa.focal / (DISTINCT * size_a)), np.floor(fit.xb * ob.focal / (DISTINCT * size_b))]
    )  # (M, 4) cell of each inlier in both images
    fit.distinct = len(np.unique(cells, axis=0))
    if fit.distinct < MIN_DISTINCT:
        # a handful of places explain any epipolar geometry (and every time offset): nothing to trust
        fit.degenerate = f"few distinct positions ({fit.distinct} < {MIN_DISTINCT})"
    else:
        fit.degenerate = _degeneracy(fit.xa, fit.xb, thr)


def _size(o: VideoObs) -> float:
    return float(max(o.video.width, o.video.height))


def _degeneracy(xa: np.ndarray, xb: np.ndarray, thr: float) -> str | None:
    """'line' when the inliers are collinear in an image, 'plane' when a homography explains them as well as E."""
    for x in (xa, xb):
        s = np.linalg.svd(x - x.mean(0), compute_uv=False)
        if s[1] < 0.01 * s[0] or s[1] < 3 * thr * np.sqrt(len(x)):  # thickness within noise of a line
            return "line"
    try:
        H, mask = cv2.findHomography(xa, xb, cv2.RANSAC, thr, maxIters=2000, confidence=0.999)
    except cv2.error:  # degenerate samples can assert inside OpenCV: no homography found
        return None
    if H is not None and mask is not None and mask.sum() >= 0.9 * len(xa):
        return "plane"
    return None
