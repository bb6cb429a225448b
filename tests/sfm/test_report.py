"""register_report.json's per-video `failed`: runs of unposed frames, not one entry per frame (sfm/report.py)."""

from __future__ import annotations

import pycolmap

from sfm.plan import FramePose
from sfm.report import _failed_runs


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
