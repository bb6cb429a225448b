"""Initial poses: the best pair's relative pose, then each further camera by PnP on the triangulated trajectory."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from sfm.subject.geometry import project, triangulate
from sfm.subject.observations import VideoObs, interpolate
from sfm.subject.pairs import PairFit

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class Knots:
    """The trajectory: 3D samples of every point on a uniform grid of global times."""

    t0: float
    h: float  # grid step (s)
    X: np.ndarray  # (T, P, 3), NaN = not triangulated

    @property
    def times(self) -> np.ndarray:
        return self.t0 + self.h * np.arange(len(self.X))  # (T,)


def make_knots(obs: list[VideoObs], offsets: np.ndarray, n_points: int) -> Knots:
    used = [i for i in range(len(obs)) if np.isfinite(offsets[i])]
    h = float(np.median([obs[i].period for i in used]))
    if n_points >= 4:  # many points: knots every other frame keep the bundle small
        h *= 2
    lo = min(obs[i].times[0] + offsets[i] for i in used)
    hi = max(obs[i].times[-1] + offsets[i] for i in used)
    T = int(np.ceil((hi - lo) / h)) + 2
    return Knots(t0=lo - h / 2, h=h, X=np.full((T, n_points, 3), np.nan))


def retriangulate(
    knots: Knots,
    obs: list[VideoObs],
    offsets: np.ndarray,
    poses: dict[int, tuple[np.ndarray, np.ndarray]],
    inlier_px: float,
) -> None:
    """Multi-view DLT at every knot from the posed cameras' interpolated observations; gross errors -> NaN."""
    cams = sorted(poses)
    tau = knots.times
    x = np.stack(
        [interpolate(obs[c].norm, obs[c].times, tau - offsets[c], 2.5 * obs[c].period) for c in cams], axis=2
    )  # (T, P, C, 2)
    P = np.stack([np.hstack([poses[c][0], poses[c][1][:, None]]) for c in cams])  # (C, 3, 4)
    X = triangulate(P, x)  # (T, P, 3)
    bad = ~np.isfinite(X[..., 0])
    for j, c in enumerate(cams):
        uv, depth = project(*poses[c], X)
        err = np.linalg.norm(uv - x[:, :, j], axis=-1) * obs[c].focal
        seen = np.isfinite(x[:, :, j, 0])
        bad |= seen & ((depth <= 0) | (err > 4 * inlier_px))
    X[bad] = np.nan
    knots.X = X


def pnp(c: VideoObs, offset: float, knots: Knots, inlier_px: float) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Pose of camera c from its observations and the trajectory interpolated at its frame times."""
    X = interpolate(knots.X, knots.times, c.times + offset, 2.5 * knots.h)  # (F, P, 3)
    ok = np.isfinite(X[..., 0]) & np.isfinite(c.norm[..., 0])
    if ok.sum() < 6:
        return None
    obj, img = X[ok].astype(np.float64), c.norm[ok].astype(np.float64)
    try:
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            np.eye(3),
            None,
            iterationsCount=2000,
            reprojectionError=2 * inlier_px / c.focal,
            confidence=0.9999,
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error:  # degenerate samples (a few positions repeated) can assert inside OpenCV: no pose
        return None
    if not found or inl is None or len(inl) < 6:
        return None
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], np.eye(3), None, rvec, tvec)
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), len(inl)


def initial_poses(
    obs: list[VideoObs],
    offsets: np.ndarray,
    fits: list[PairFit],
    knots: Knots,
    inlier_px: float,
    failed: dict[str, str],
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """cam_from_world of every camera that can be chained (first camera of the best pair at the origin)."""
    usable = [f for f in fits if f.usable and np.isfinite(offsets[f.a]) and np.isfinite(offsets[f.b])]
    best = max(usable, key=lambda f: (not f.ambiguous, f.inliers))  # a trusted offset first
    E = best.E
    # re-estimate E in the current normalized coordinates (focal estimates may have changed since the search)
    try:
        E2, _mask = cv2.findEssentialMat(
            best.xa,
            best.xb,
            np.eye(3),
            method=cv2.USAC_MAGSAC,
            prob=0.9999,
            threshold=inlier_px / np.sqrt(obs[best.a].focal * obs[best.b].focal),
        )
    except cv2.error:  # USAC asserts on some degenerate samples: the search's model stands
        E2 = None
    if E2 is not None and E2.shape == (3, 3):
        E = E2
    assert E is not None  # usable pairs have a model
    _, R, t, _ = cv2.recoverPose(E, best.xa, best.xb, np.eye(3))
    poses = {best.a: (np.eye(3), np.zeros(3)), best.b: (R, t.ravel())}
    retriangulate(knots, obs, offsets, poses, inlier_px)
    todo = {i for i in range(len(obs)) if np.isfinite(offsets[i]) and i not in poses and obs[i].name not in failed}
    while todo:
        links = {i: sum(f.inliers for f in usable if {f.a, f.b} & set(poses) and i in (f.a, f.b)) for i in todo}
        nxt = max(todo, key=lambda i: (links[i], obs[i].count()))
        todo.discard(nxt)
        got = pnp(obs[nxt], float(offsets[nxt]), knots, inlier_px)
        if got is None:
            failed[obs[nxt].name] = "too few of its observations meet the trajectory triangulated from the others"
            continue
        R, t, n = got
        log.info("camera %s: PnP with %d inliers", obs[nxt].name, n)
        poses[nxt] = (R, t)
        retriangulate(knots, obs, offsets, poses, inlier_px)
    return poses
