"""register_report.json's per-video `failed` and `posed`: runs of frames, not one entry per frame (sfm/report.py)."""

from __future__ import annotations

import pycolmap

from sfm.plan import FramePose
from sfm.report import _failed_runs, _posed_runs, posed_frames


def test_unposed_frames_are_reported_as_runs_split_by_reason_and_by_posed_frames() -> None:
    posed = FramePose(pose=pycolmap.Rigid3d(), source="static")
    per_frame = {f: FramePose(pose=None, reason="no model") for f in range(0, 1000)}
    per_frame |= {1000: posed, 1001: FramePose(pose=None, reason="no model")}
    per_frame |= {f: FramePose(pose=None, reason="blurred") for f in range(1002, 1005)}
    per_frame[1005] = FramePose(pose=None)
    assert _failed_runs(per_frame) == [
        {"first": 0, "last": 999, "frames": 1000, "reason": "no model"},
        {"first": 1001, "last": 1001, "frames": 1, "reason": "no model"},  # a posed frame between: a new run
        {"first": 1002, "last": 1004, "frames": 3, "reason": "blurred"},
        {"first": 1005, "last": 1005, "frames": 1, "reason": "unknown"},
    ]
    assert _failed_runs({1000: posed}) == []


def test_a_static_or_subject_video_is_one_posed_run_and_pnp_frames_keep_their_inliers() -> None:
    static = {f: FramePose(pose=pycolmap.Rigid3d(), source="static") for f in range(500)}
    assert _posed_runs(static) == [{"first": 0, "last": 499, "frames": 500, "path": "static", "inliers": None}]
    subject = {f: FramePose(pose=pycolmap.Rigid3d(), source="subject", inliers=2256) for f in range(100)}
    assert _posed_runs(subject) == [{"first": 0, "last": 99, "frames": 100, "path": "subject", "inliers": 2256}]
    moving = {0: FramePose(pose=pycolmap.Rigid3d(), source="sfm", inliers=300)}
    moving |= {f: FramePose(pose=pycolmap.Rigid3d(), source="pnp", inliers=40 + f) for f in (1, 2)}
    moving |= {3: FramePose(pose=None, reason="lost"), 5: FramePose(pose=pycolmap.Rigid3d(), source="static")}
    moving[6] = FramePose(pose=pycolmap.Rigid3d(), source="static")  # after a gap in the frame numbers: a new run
    runs = _posed_runs(moving)
    assert [(r["first"], r["last"], r["path"], r["inliers"]) for r in runs] == [
        (0, 0, "sfm", 300),
        (1, 1, "sift", 41),
        (2, 2, "sift", 42),
        (5, 6, "static", None),
    ]
    frames = posed_frames({"posed": runs})
    assert sorted(frames) == [0, 1, 2, 5, 6] and frames[2] == {"path": "sift", "inliers": 42}
    gap = {
        0: FramePose(pose=pycolmap.Rigid3d(), source="static"),
        2: FramePose(pose=pycolmap.Rigid3d(), source="static"),
    }
    assert len(_posed_runs(gap)) == 2  # frames 0 and 2 only: never a run that claims frame 1
