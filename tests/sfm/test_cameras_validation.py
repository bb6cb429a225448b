"""validate_cameras checks all frames at once when they clearly pass, else frame by frame (naming the first fault)."""

import numpy as np
import pytest

from dynrecon.errors import InputError
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, _clearly_valid, validate_cameras


def _frame(number, **changes):
    values = {
        "frame": number,
        "K": np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]),
        "R": np.eye(3),
        "t": np.array([0.0, 0.0, 5.0]),
        "dist": np.array([0.1, -0.01, 0.0, 0.0]),
    }
    values.update(changes)
    return FrameCamera(**values)


def _set(*frames, second=True):
    videos = [VideoCameras(name="a", width=640, height=480, frames=list(frames))]
    if second:
        videos.append(VideoCameras(name="b", width=640, height=480, frames=[_frame(0, dist=None)]))
    return CameraSet(videos=videos)


def _tilted(epsilon):
    """A rotation with |R R^T - I| of about epsilon (a scaled column)."""
    R = np.eye(3)
    R[:, 0] *= 1 + epsilon / 2
    return R


def test_valid_frames_pass_at_once():
    cameras = _set(_frame(0), _frame(1))
    assert _clearly_valid(cameras)
    validate_cameras(cameras)
    assert _clearly_valid(CameraSet(videos=[]))


def test_a_rotation_near_the_tolerance_is_checked_frame_by_frame_and_passes():
    cameras = _set(_frame(0), _frame(1, R=_tilted(8e-6)))
    assert not _clearly_valid(cameras)
    validate_cameras(cameras)


@pytest.mark.parametrize(
    ("frames", "message"),
    [
        ((_frame(0), _frame(1, R=_tilted(1e-3))), "frame 1.*is not a rotation"),
        ((_frame(0), _frame(1, R=-np.eye(3))), "is not a rotation"),
        ((_frame(0), _frame(0)), "frame appears twice"),
        ((_frame(0, K=np.array([[800.0, 0, 320], [1e-3, 800, 240], [0, 0, 1]])),), '"K" must be'),
        ((_frame(0, K=np.diag([0.5, 800.0, 1.0])),), "fx = 0.5 px is implausible"),
        ((_frame(0, t=np.array([0.0, 0.0, 1e10])),), '"t"'),
        ((_frame(0, dist=np.array([1e4, 0.0, 0.0, 0.0])),), '"dist"'),
        ((_frame(0, K=np.full((3, 3), np.nan)),), "NaN or infinity"),
    ],
)
def test_faults_are_named_frame_by_frame(frames, message):
    cameras = _set(*frames)
    assert not _clearly_valid(cameras)
    with pytest.raises(InputError, match=message):
        validate_cameras(cameras)


def test_a_repeated_video_name_is_named():
    cameras = _set(_frame(0))
    cameras.videos[1].name = "a"
    assert not _clearly_valid(cameras)
    with pytest.raises(InputError, match="appears twice"):
        validate_cameras(cameras)
