"""The folds' comparison of `sfm.subject.stability`: one camera a fold poses badly is the only one flagged."""

from __future__ import annotations

import numpy as np

from sfm.subject import SubjectCamera, SubjectOptions, SubjectResult
from sfm.subject.stability import MAX_CENTRE, MAX_ROTATION_DEG, _robust_errors, check_stability
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


def test_every_fold_change_is_reported_and_one_fold_past_the_limit_refuses() -> None:
    """Each fold's solve is scripted: cam1 turned 8 deg in one fold, cam3 in two. Both are refused (one fold past
    the limit is enough), each message lists every fold's change, and the report carries them."""
    from sfm.subject import SubjectOptions, SubjectResult
    from sfm.subject.stability import check_stability

    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=5, duration=6.0, seed=1)
    whole = SubjectResult(cameras=_cameras(truth.R, truth.t), pairs=[], failed={}, metric=False)
    turned = {0: {"cam1", "cam3"}, 1: {"cam3"}, 2: set()}  # fold -> cameras its solve turns
    calls: list[int] = []

    def solve(fold_tracks: object, options: SubjectOptions) -> SubjectResult:
        fold = len(calls)
        calls.append(fold)
        R = [
            _rotation(np.array([0.0, 1.0, 0.0]), 8.0) @ r if f"cam{i}" in turned[fold] else r
            for i, r in enumerate(truth.R)
        ]
        centres = [-r.T @ t for r, t in zip(truth.R, truth.t, strict=True)]
        t = [-r @ c for r, c in zip(R, centres, strict=True)]  # turned about the centre: only the rotation moves
        return SubjectResult(cameras=_cameras(R, t), pairs=[], failed={}, metric=False)

    stability = check_stability(tracks, videos, whole, SubjectOptions(), solve=solve)

    assert len(calls) == 3
    assert sorted(stability.unstable) == ["cam1", "cam3"]
    assert "8.0, 8.0, 0.0 deg" in stability.unstable["cam3"] and "in 2 of 3 folds" in stability.unstable["cam3"]
    assert "8.0, 0.0, 0.0 deg" in stability.unstable["cam1"] and "in 1 of 3 folds" in stability.unstable["cam1"]
    assert abs(stability.rotation_deg["cam1"] - 8.0) < 0.1
    assert stability.to_json()["rotation_folds_deg"]["cam3"][:2] == [8.0, 8.0]
    assert all(v < 0.1 for v in stability.rotation_folds["cam0"])


def test_folds_of_a_loosened_solution_start_from_its_focals() -> None:
    """A solution whose focal prior was loosened has its folds solved at its focals, with the same loose prior;
    one solved at the self-calibrated prior leaves the folds to self-calibrate (their options say neither)."""
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=3, duration=6.0, seed=1)
    seen: list[SubjectOptions] = []

    def solve(fold_tracks: object, options: SubjectOptions) -> SubjectResult:
        seen.append(options)
        return SubjectResult(cameras=_cameras(truth.R, truth.t), pairs=[], failed={}, metric=False)

    for sigma in (0.5, None):
        whole = SubjectResult(cameras=_cameras(truth.R, truth.t), pairs=[], failed={}, metric=False, focal_sigma=sigma)
        seen.clear()
        assert not check_stability(tracks, videos, whole, SubjectOptions(), solve=solve).unstable
        assert len(seen) == 3
        if sigma is None:
            assert all(o.focals is None and o.focal_sigma is None for o in seen)
        else:
            assert all(o.focal_sigma == sigma for o in seen)
            assert all(o.focals == {f"cam{i}": 1000.0 for i in range(3)} for o in seen)


def test_two_cameras_without_intrinsics_are_not_trusted() -> None:
    """One pair of views aimed at one subject does not determine self-calibrated focals, and its folds (relative
    rotation only) move with a wrong focal: such a pair is refused whatever its folds; with known intrinsics a fold
    turning it by 3 deg stands."""
    import dataclasses

    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=2, duration=6.0, seed=1)
    whole = SubjectResult(cameras=_cameras(truth.R, truth.t), pairs=[], failed={}, metric=False)
    centres = [-r.T @ t for r, t in zip(truth.R, truth.t, strict=True)]
    calls: list[int] = []

    def solve(fold_tracks: object, options: SubjectOptions) -> SubjectResult:
        calls.append(1)
        R = [truth.R[0], _rotation(np.array([0.0, 1.0, 0.0]), 3.0) @ truth.R[1]]
        t = [-r @ c for r, c in zip(R, centres, strict=True)]
        return SubjectResult(cameras=_cameras(R, t), pairs=[], failed={}, metric=False)

    known = check_stability(tracks, videos, whole, SubjectOptions(), solve=solve)
    assert not known.unstable and len(calls) == 3
    one_unknown = [videos[0], dataclasses.replace(videos[1], K=None, dist=None)]
    self_calibrated = check_stability(tracks, one_unknown, whole, SubjectOptions(), solve=solve)
    assert len(calls) == 3  # no fold solved: nothing they show would be trusted
    assert sorted(self_calibrated.unstable) == ["cam0", "cam1"]
    assert "two cameras with self-calibrated focal lengths" in self_calibrated.unstable["cam0"]
    # beside videos the background posed (a handheld phone), whose poses constrain the focals, the folds decide
    beside_posed = check_stability(tracks, one_unknown, whole, SubjectOptions(), solve=solve, alone=False)
    assert not beside_posed.unstable and len(calls) == 6
