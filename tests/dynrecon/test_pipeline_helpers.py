"""Parts of `run` (dynrecon/pipeline.py): the solve when registration left a tracked video unposed, and the
exports' unit label."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from synthetic_motion import smooth_motion

from dynrecon.pipeline import PipelineOptions, Registration, _solve_posed_videos, _world_units
from reconstruct.outputs.points import read_points
from reconstruct.stage import SolveOptions
from sfm.cameras import write_cameras
from sfm.options import ImportCalibrationOptions
from simulation.simulate import SimulationOptions, simulate_capture
from tracking.tracks import Tracks, write_tracks


def test_tracks_of_a_video_registration_did_not_pose_are_left_out(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    capture = simulate_capture(smooth_motion(60, 4), 120.0, SimulationOptions(seed=3))
    cameras = write_cameras(tmp_path / "cameras.json", capture.cameras)
    t = capture.tracks
    ghost = [("cam_unposed", int(f), p, 100.0 + f, 200.0) for f in range(10) for p in t.point_names()]
    rows = [(v, int(f), p, float(x), float(y)) for v, f, p, (x, y) in zip(t.video, t.frame, t.point, t.xy, strict=True)]
    tracks = write_tracks(tmp_path / "tracks.csv", Tracks.from_rows(rows + ghost))

    with caplog.at_level(logging.WARNING, logger="dynrecon.pipeline"):
        _solve_posed_videos(cameras, tracks, tmp_path / "out", SolveOptions(recording=None))

    # a video the cameras do not list was not given to this run (dropped), not left unposed by registration
    assert any("cam_unposed" in r.message and "not among this run's videos" in r.message for r in caplog.records)
    assert not any("registration posed none" in r.message for r in caplog.records)
    points = read_points(tmp_path / "out" / "points3d.csv")
    assert "cam_unposed" not in set(points.videos) and np.isfinite(points.xyz).any()


@pytest.mark.parametrize(
    ("subject", "calibration_scale", "label"),
    [
        ({"used": True, "metric": True, "units": "m"}, None, "m"),  # --scale or --board
        ({"used": True, "metric": True, "units": None}, None, "mm"),  # the background's anchors: its own scale
        (None, None, "mm"),  # background SfM: arbitrary, a nominal label
        (None, 1.0, "m"),  # a calibration in metres
        (None, 1000.0, "mm"),  # imported with --scale 1000
    ],
)
def test_the_export_label_is_the_worlds_unit(
    tmp_path: Path, subject: dict | None, calibration_scale: float | None, label: str
) -> None:
    (tmp_path / "register_report.json").write_text(json.dumps({"subject": subject}))
    options = PipelineOptions()
    if calibration_scale is not None:
        options = PipelineOptions(
            calibration=tmp_path / "calibration.toml",
            calibration_options=ImportCalibrationOptions(scale=calibration_scale),
        )
    assert _world_units(options, Registration.in_folder(tmp_path)) == label


def test_a_triggered_rig_is_exported_at_its_own_rate() -> None:
    """Frames that coincide in global time (a triggered 120 Hz rig) are one instant: 120 Hz, not the 240 Hz of two
    interleaved videos; videos that interleave (or run at 30 and 25 fps) keep the summed rate (None here)."""
    import numpy as np

    from dynrecon.pipeline import triggered_rate

    two = ["a"] * 120 + ["b"] * 120
    assert triggered_rate(np.concatenate([np.arange(120) / 120] * 2), two) == pytest.approx(120.0)
    assert triggered_rate(np.concatenate([np.arange(120) / 120, np.arange(120) / 120 + 0.004]), two) is None
    mixed = np.concatenate([np.arange(120) / 30, np.arange(100) / 25 + 0.013])
    assert triggered_rate(mixed, ["a"] * 120 + ["b"] * 100) is None
    assert triggered_rate(np.arange(5) / 30, ["a"] * 5) is None  # one video


def test_the_export_rate_is_not_lowered_by_dropped_frames() -> None:
    """A video's rate from decoder times is its median frame step: frames dropped (incomplete motion-capture frames,
    untracked stretches) leave gaps that a rate over the whole span would count as a slower camera."""
    from dynrecon.pipeline import export_rate
    from sfm.cameras import CameraSet, FrameCamera, VideoCameras

    def video(name: str, times: np.ndarray) -> VideoCameras:
        frames = [
            FrameCamera(frame=i, K=np.eye(3), R=np.eye(3), t=np.zeros(3), time=float(t)) for i, t in enumerate(times)
        ]
        return VideoCameras(name=name, width=640, height=480, frames=frames)

    steady = np.arange(120) / 60.0
    gapped = np.delete(steady, np.arange(30, 70))  # 40 frames dropped in the middle
    assert export_rate(CameraSet(videos=[video("a", steady), video("b", gapped)]), 200) == pytest.approx(120.0)
    # a video the solve left out has no rows: its rate is not the export's
    cameras = CameraSet(videos=[video("a", steady), video("b", gapped)])
    assert export_rate(cameras, 120, {"a"}) == pytest.approx(60.0)
