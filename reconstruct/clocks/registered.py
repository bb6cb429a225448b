"""Do the recovered clocks agree with the offsets that registration found? (`cameras.json` `clock_offset`)

Register's subject path fits each static video's clock offset from the subject's 2D tracks and the epipolar
geometry; the solve recovers clocks from its own evidence (W's links and the tracks). Two independent estimates of
the same offsets: where they differ by more than a frame (or three standard deviations), one of them is wrong, and
the report and a warning say which videos disagree.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from reconstruct.clocks.model import Clocks, VideoClockReport
from sfm.cameras import CameraSet

log = logging.getLogger(__name__)


def _middle(cameras: CameraSet, name: str) -> float:
    """The video's middle own time (s): decoder times, else frame / fps; 0 where neither is known."""
    video = cameras.video(name)
    times = [f.time for f in video.frames if f.time is not None]
    if len(times) < 2 and video.fps:
        times = [f.frame / video.fps for f in video.frames]
    return float(np.median(times)) if times else 0.0


def _offset_at(clock: VideoClockReport, own: float) -> float:
    """global - own at own time `own`: the clock's offset where the video's frames are (a fitted rate moves the
    offset at own time 0 away from registration's, whose rate is 1, without any disagreement in the middle)."""
    rate = clock.rate if math.isfinite(clock.rate) else 1.0
    return clock.offset + (rate - 1.0) * own + clock.drift * own**2


def _frame_period(cameras: CameraSet, name: str) -> float:
    video = cameras.video(name)
    times = np.array([f.time for f in video.frames if f.time is not None], dtype=float)
    if len(times) >= 2:
        return float(np.median(np.diff(np.sort(times))))
    return 1.0 / video.fps if video.fps else math.nan


def check_registered_clocks(cameras: CameraSet, clocks: Clocks) -> dict[str, Any] | None:
    """None when fewer than two videos have both a registered offset and a recovered clock; else per video the
    registered and recovered offsets (each in the middle of its video's frames) relative to a common reference
    video, their difference and whether they agree."""
    registered: dict[str, float] = {v.name: v.clock_offset for v in cameras.videos if v.clock_offset is not None}
    solved = {c.name: c for c in clocks.videos if c.identified and math.isfinite(c.offset)}
    common = [name for name in registered if name in solved]
    if len(common) < 2:
        return None
    reference = common[0]
    videos: list[dict[str, Any]] = []
    for name in common[1:]:
        expected = registered[name] - registered[reference]
        found = _offset_at(solved[name], _middle(cameras, name)) - _offset_at(
            solved[reference], _middle(cameras, reference)
        )
        std = math.hypot(_estimate_std(solved[name]), _estimate_std(solved[reference]))
        period = _frame_period(cameras, name)
        tolerance = max(period if math.isfinite(period) else 0.0, 3 * std if math.isfinite(std) else 0.0)
        videos.append(
            {
                "video": name,
                "registered_s": round(expected, 6),
                "recovered_s": round(found, 6),
                "difference_s": round(found - expected, 6),
                "tolerance_s": round(tolerance, 6),
                "agree": bool(abs(found - expected) <= tolerance),
            }
        )
    disagree = [str(v["video"]) for v in videos if not v["agree"]]
    if disagree:
        log.warning(
            "recovered clocks of %s disagree with %s (relative to %s); see report.json clocks.registration_check",
            ", ".join(disagree),
            offsets_source(cameras),
            reference,
        )
    return {"reference": reference, "videos": videos, "agree": not disagree}


def _estimate_std(clock: VideoClockReport) -> float:
    """The clock's offset_std as estimated (a refit's move widens the reported one, not the agreement's tolerance:
    a clock the polish moved by a frame would let offsets three frames off agree)."""
    return clock.estimate_std if math.isfinite(clock.estimate_std) else clock.offset_std


def all_declared(cameras: CameraSet) -> bool:
    """Whether every video's clock_offset was declared by the user (--synchronized, --offsets), none estimated."""
    offsets = [v for v in cameras.videos if v.clock_offset is not None]
    return bool(offsets) and all(v.clock_declared for v in offsets)


def offsets_source(cameras: CameraSet) -> str:
    """How the log names cameras.json's clock offsets: the user's, or registration's estimates."""
    return "the declared clock offsets" if all_declared(cameras) else "registration's offsets"
