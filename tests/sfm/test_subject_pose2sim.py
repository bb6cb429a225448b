"""The Pose2Sim subject-path benchmarks' helpers (benchmarks/pose2sim_check.py, benchmarks/register_real.py): the
comparison's gauge, the registered clock offsets carried to the solve, and the union of detections and markers."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks import pose2sim_check as check
from benchmarks import register_real as real
from sfm.cameras import CameraSet, FrameCamera, VideoCameras
from tracking.tracks import Tracks


def _cameras(offsets: list[float | None]) -> CameraSet:
    videos = []
    for k, offset in enumerate(offsets):
        frames = [FrameCamera(frame=f, time=f / 60.0, K=np.eye(3), R=np.eye(3), t=np.zeros(3)) for f in range(12)]
        videos.append(
            VideoCameras(name=f"cam0{k + 1}", width=10, height=10, fps=60.0, frames=frames, clock_offset=offset)
        )
    return CameraSet(videos=videos)


def test_similarity_distances_remove_only_the_gauge() -> None:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(40, 3)) * 500.0
    R = cv2.Rodrigues(np.array([0.3, -0.2, 0.9]))[0]
    moved = 1.7 * points @ R.T + np.array([10.0, -300.0, 42.0])
    np.testing.assert_allclose(check.similarity_distances(moved, points), 0.0, atol=1e-8)
    # A shape error stays: one point 10 mm off is still about 10 mm off after the fit.
    moved[0] += 1.7 * R @ np.array([10.0, 0.0, 0.0])
    assert 8.0 < check.similarity_distances(moved, points)[0] < 10.5
    assert np.isnan(check.similarity_distances(points[:2], points[:2])).all()  # too few to fit


def test_desynchronize_and_shifted_clocks_keep_the_registered_offsets() -> None:
    """The solve checks its recovered clocks against cameras.json's clock_offset: the benchmark must pass them on,
    moved with the times it shifts (own + offset names the same instant)."""
    cameras = _cameras([0.0, 0.015, None, -0.01])
    rows = [(f"cam0{k + 1}", f, "p", 1.0, 2.0) for k in range(4) for f in range(12)]
    desync, _ = check.desynchronize(cameras, Tracks.from_rows(rows), window=(0, 11))
    assert [v.clock_offset for v in desync.videos] == [0.0, 0.015, None, -0.01]
    shifted = check.shift_clocks(desync, (0.0, 0.37, -0.81, 1.23))
    for before, after in zip(desync.videos, shifted.videos, strict=True):
        if before.clock_offset is None:
            assert after.clock_offset is None
            continue
        for a, b in zip(before.frames, after.frames, strict=True):
            assert a.time is not None and b.time is not None and after.clock_offset is not None
            assert b.time + after.clock_offset == pytest.approx(a.time + before.clock_offset)


def test_union_tracks_keeps_every_row_and_the_extra_columns() -> None:
    detections = Tracks.from_rows(
        [("cam01", 0, "Nose", 1.0, 2.0), ("cam02", 0, "Nose", 3.0, 4.0)], score=["0.9", "0.8"]
    )
    markers = Tracks.from_rows([("cam01", 0, "L_hand", 5.0, 6.0)], source=["label"])
    union = check.union_tracks(detections, markers)
    assert union.video == ["cam01", "cam02", "cam01"] and union.point == ["Nose", "Nose", "L_hand"]
    np.testing.assert_array_equal(union.xy, [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    assert union.extra == {"score": ["0.9", "0.8", ""], "source": ["", "", "label"]}


def test_desynchronized_labels_follow_the_dropped_frames(tmp_path: Path) -> None:
    out = real.desynchronized_labels(tmp_path / "labels.csv")
    with real.LABELS.open(newline="", encoding="utf-8") as source:
        original = list(csv.DictReader(source))
    with out.open(newline="", encoding="utf-8") as target:
        renumbered = list(csv.DictReader(target))
    expected = [
        (r["video"], int(r["frame"]) - real.DROPPED_POSE2SIM[r["video"]], r["point"], r["x"])
        for r in original
        if int(r["frame"]) >= real.DROPPED_POSE2SIM[r["video"]]
    ]
    assert [(r["video"], int(r["frame"]), r["point"], r["x"]) for r in renumbered] == expected
    assert len(expected) < len(original)  # the frame-0 labels of the cameras that lost frames are gone
