"""A moving camera's poses that jump off the path their neighbouring frames agree on (`sfm.path_check`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sfm.path_check import path_spikes


def _pan(frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A handheld pan: centres drifting 0.02 per frame with 3 mm of shake, turning 0.8 deg per frame."""
    rng = np.random.default_rng(seed)
    centres = np.c_[0.02 * np.arange(frames), 0.01 * np.sin(np.arange(frames) / 5), np.zeros(frames)]
    centres += rng.normal(0, 0.003, centres.shape)
    rotations = Rotation.from_euler("y", (0.8 * np.arange(frames) + rng.normal(0, 0.1, frames))[:, None], degrees=True)
    return centres, rotations.as_matrix()


def test_a_smooth_handheld_path_has_no_spike() -> None:
    centres, rotations = _pan(60)
    assert path_spikes(centres, rotations) == []
    # a whip pan: 30 deg per frame throughout is the camera's motion, not a spike
    whip = Rotation.from_euler("y", 30.0 * np.arange(20)[:, None], degrees=True).as_matrix()
    assert path_spikes(centres[:20], whip) == []


def test_a_frame_far_off_or_turned_away_and_back_is_a_spike() -> None:
    """A keyframe held by two observations 1,231 units off a phone's path, and a frame turned 35 deg and back within
    two frames (a helper's handheld clips: both written as posed, exit 0)."""
    centres, rotations = _pan(60)
    centres[9] = [241.0, -74.0, 1231.0]
    rotations[30] = Rotation.from_euler("x", 35, degrees=True).as_matrix() @ rotations[30]
    assert path_spikes(centres, rotations) == [9, 30]


def test_a_jump_on_weak_support_is_unposed_and_one_its_matches_support_is_kept() -> None:
    """The jump of a frame posed from 2 observations among frames of hundreds is dropped and said; a frame turned
    40 deg for one frame whose own SIFT matches (487 inliers) support it is the camera's motion (test_inbetween)."""
    from pathlib import Path

    import pycolmap

    from sfm.frames import Resize
    from sfm.path_check import drop_spikes
    from sfm.plan import FramePose, VideoPlan
    from sfm.video import ProbedVideo

    centres, rotations = _pan(20)
    centres[5] = [241.0, -74.0, 1231.0]
    rotations[12] = Rotation.from_euler("x", 40, degrees=True).as_matrix() @ rotations[12]
    info = ProbedVideo(path=Path("b1.mp4"), name="b1", width=960, height=540, times=np.arange(20) / 30, nominal_fps=30)
    plan = VideoPlan(
        info=info,
        resize=Resize(scale=1.0, width=960, height=540),
        sfm_frames=np.zeros(0, dtype=np.int64),
        wanted=np.arange(20),
        static=False,
    )
    inliers = {f: 500 for f in range(20)} | {5: 2, 12: 487}
    results = {
        "b1": {
            f: FramePose(
                pose=pycolmap.Rigid3d(pycolmap.Rotation3d(rotations[f]), -rotations[f] @ centres[f]),
                source="sfm",
                inliers=inliers[f],
            )
            for f in range(20)
        }
    }
    warnings: list[str] = []
    drop_spikes([plan], results, warnings)
    unposed = [f for f, r in results["b1"].items() if r.pose is None]
    assert unposed == [5] and len(warnings) == 1 and warnings[0].startswith("b1: frame(s) 5 left unposed")
