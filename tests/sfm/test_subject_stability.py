"""The folds' comparison of `sfm.subject.stability`: one camera a fold poses badly is the only one flagged."""

from __future__ import annotations

import numpy as np

from sfm.subject import SubjectCamera
from sfm.subject.stability import MAX_CENTRE, MAX_ROTATION_DEG, _robust_errors
from sfm.subject.synthetic import make_rig


def _cameras(R: list[np.ndarray], t: list[np.ndarray]) -> list[SubjectCamera]:
    K = np.diag([1000.0, 1000.0, 1.0])
    return [
        SubjectCamera(name=f"cam{i}", K=K, dist=None, R=r, t=tt, offset=0.0, inliers=100, residual_px=1.0)
        for i, (r, tt) in enumerate(zip(R, t, strict=True))
    ]


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.radians(degrees) * axis / np.linalg.norm(axis))[0]


def test_one_badly_posed_camera_spoils_no_other() -> None:
    _, _, truth = make_rig(kind="skeleton", n_cameras=5, seed=1)
    whole = _cameras(truth.R, truth.t)
    # the fold's solution: another frame and scale, small noise, and cam2 turned by 20 deg about its centre
    Q, s, T = _rotation(np.array([0.3, 1.0, 0.2]), 40.0), 2.5, np.array([1.0, -2.0, 0.5])
    rng = np.random.default_rng(0)
    R_fold, t_fold = [], []
    for i, (R, t) in enumerate(zip(truth.R, truth.t, strict=True)):
        centre = s * Q @ (-R.T @ t) + T + rng.normal(0, 0.005, 3)
        R_new = R @ Q.T
        if i == 2:
            R_new = _rotation(np.array([0.0, 1.0, 0.0]), 20.0) @ R_new
        R_fold.append(R_new)
        t_fold.append(-R_new @ centre)
    centres = truth.centres()
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max() * 2)

    errors = _robust_errors(_cameras(R_fold, t_fold), whole, spread)

    flagged = sorted(n for n, (c, a) in errors.items() if c > MAX_CENTRE or a > MAX_ROTATION_DEG)
    assert flagged == ["cam2"] and abs(errors["cam2"][1] - 20.0) < 0.5
    assert all(a < 0.5 and c < 0.01 for n, (c, a) in errors.items() if n != "cam2")
