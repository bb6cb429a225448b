"""Whether each video's recovered clock puts its frames at times another video also filmed.

A clock placed a second off on a one-second capture (a handheld 3-marker trial, its tracks' search fooled by the
sway) passed every check of the tracks path: its video's span then barely meets any other's, and its points rest on
no second view. Said in report.json `clocks.warnings`, not refused: a phone started late may truly overlap little.
"""

from __future__ import annotations

import numpy as np

from reconstruct.clocks.model import Clocks

__all__ = ["MIN_SHARED", "lonely_videos"]

MIN_SHARED = 0.25  # of a video's own span, the most it shares with one other video under the recovered clocks


def lonely_videos(clocks: Clocks) -> list[str]:
    """One warning per video whose span of global time shares under MIN_SHARED of itself with every other video's."""
    names = [c.name for c in clocks.videos]
    spans: dict[str, tuple[float, float]] = {}
    frame_videos = np.asarray(clocks.frame_videos)
    for name in names:
        times = clocks.global_time[(frame_videos == name) & np.isfinite(clocks.global_time)]
        if len(times) >= 2 and times.max() > times.min():
            spans[name] = (float(times.min()), float(times.max()))
    warnings = []
    for name, (lo, hi) in spans.items():
        others = [(min(hi, end) - max(lo, start), other) for other, (start, end) in spans.items() if other != name]
        if not others:
            continue
        shared, best = max(others)
        if shared < MIN_SHARED * (hi - lo):
            warnings.append(
                f"video {name!r}: under its recovered clock it shares {max(shared, 0.0):.2f} s of its {hi - lo:.2f} s "
                f"with any other video (most with {best!r}): its clock is likely wrong, or it filmed at other times; "
                "its points there rest on no second view"
            )
    return warnings
