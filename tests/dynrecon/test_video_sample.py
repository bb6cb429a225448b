"""The embedded video sample: the checked-in files agree with each other, and the generator makes them."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from reconstruct.outputs.points import read_points
from sfm.cameras import read_cameras
from tracking.workspace import read_labels

SAMPLE = Path(__file__).resolve().parents[2] / "data_samples" / "video_sample"


def _project(camera, xyz: np.ndarray) -> np.ndarray:
    x = (xyz @ camera.R.T + camera.t) @ camera.K.T
    return x[..., :2] / x[..., 2:]


def _check_sample(folder: Path, max_label_error_px: float) -> None:
    meta = json.loads((folder / "sample.json").read_text())
    cameras = read_cameras(folder / "truth_cameras.json")
    truth = read_points(folder / "truth.csv")
    index = truth.index()
    for video in meta["videos"]:
        capture = cv2.VideoCapture(str(folder / f"{video['name']}.mp4"))
        try:
            assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(video["fps"], rel=1e-3)
            code = int(capture.get(cv2.CAP_PROP_FOURCC))
            assert "".join(chr((code >> 8 * k) & 0xFF) for k in range(4)) in ("vp09", "VP90")  # VP9: rerun plays it
            count = 0
            while capture.read()[0]:
                count += 1
        finally:
            capture.release()
        assert count == video["frames"]
        assert len(cameras.video(video["name"]).frames) == count
        # truth: every frame, at its true capture time (start + frame / fps)
        for frame in range(count):
            row = index[(video["name"], frame)]
            assert truth.extra["time"][row, 0] == pytest.approx(video["start_s"] + frame / video["fps"])
    # Labels are the true projections of the joints plus a little noise, on every 10th frame only.
    labels = read_labels(folder / "labels.csv")
    points = {name: i for i, name in enumerate(truth.point_names)}
    errors = []
    for video, by_point in labels.items():
        for point, by_frame in by_point.items():
            for frame, xy in by_frame.items():
                assert frame % meta["label_every"] == 0
                assert xy is not None
                camera = next(f for f in cameras.video(video).frames if f.frame == frame)
                true_uv = _project(camera, truth.xyz[index[(video, frame)], points[point]])
                errors.append(float(np.linalg.norm(true_uv - np.asarray(xy))))
    assert errors
    assert max(errors) < max_label_error_px
    assert np.median(errors) < 1.0


def test_checked_in_sample_is_consistent():
    if not (SAMPLE / "cam0.mp4").is_file():
        pytest.skip("data_samples/video_sample is not generated")
    _check_sample(SAMPLE, max_label_error_px=3.0)
    total = sum(p.stat().st_size for p in SAMPLE.iterdir())
    assert total < 4.5e6  # small enough for the repository


def test_generator_makes_a_consistent_sample(tmp_path, monkeypatch):
    """A small, fast variant of the generator (tiny images, few frames) through the same code."""
    import data_samples.make_video_sample as make

    monkeypatch.setattr(make, "WIDTH", 160)
    monkeypatch.setattr(make, "HEIGHT", 120)
    monkeypatch.setattr(
        make, "SHOTS", tuple(replace(s, num_frames=n) for s, n in zip(make.SHOTS, (11, 9, 7), strict=True))
    )
    make.main(tmp_path)
    _check_sample(tmp_path, max_label_error_px=3.0)
    truth = read_points(tmp_path / "truth.csv")
    assert truth.point_names[:4] == ["pelvis", "spine", "neck", "head"]
    # The subject stands in the room (metres * 1000 = mm): feet near the floor, head below the ceiling.
    assert np.nanmin(truth.xyz[..., 2]) > -60 and np.nanmax(truth.xyz[..., 2]) < 3000
    # Different start times: the first frames of the three videos are captured at three different instants.
    first = [truth.extra["time"][truth.index()[(f"cam{i}", 0)], 0] for i in range(3)]
    assert len(set(first)) == 3
