"""A video whose recovered clock puts it at times no other video filmed is said in report.json's clock warnings."""

from __future__ import annotations

import numpy as np

from reconstruct.clocks.model import ClockModel, Clocks, TimeSource, VideoClockReport
from reconstruct.clocks.overlap import lonely_videos


def _clocks(starts: dict[str, float], span: float = 1.0, frames: int = 30) -> Clocks:
    names = list(starts)
    own = np.tile(np.linspace(0, span, frames), len(names))
    videos = [n for n in names for _ in range(frames)]
    return Clocks(
        model=ClockModel.OFFSET,
        reference=names[0],
        videos=[VideoClockReport(name=n, time_source=TimeSource.FPS, offset=starts[n], rate=1.0) for n in names],
        frame_videos=videos,
        frames=np.tile(np.arange(frames), len(names)),
        own_time=own,
        global_time=own + np.repeat([starts[n] for n in names], frames),
        global_std=np.zeros(len(own)),
    )


def test_a_clock_a_capture_away_from_every_other_video_is_said() -> None:
    """The handheld 3-marker trial: cam1's clock 0.86 s off on a 0.96 s capture (11 % shared), cam0's 1.13 s off
    (nothing shared); every check of the tracks path had passed."""
    warnings = lonely_videos(_clocks({"cam0": 0.0, "cam1": 0.86, "cam2": 0.02}))
    assert len(warnings) == 1 and warnings[0].startswith(
        "video 'cam1': under its recovered clock it shares 0.16 s of its 1.00 s"
    )
    assert lonely_videos(_clocks({"cam0": 1.13, "cam1": 0.0, "cam2": -0.05}))[0].startswith("video 'cam0'")
    assert lonely_videos(_clocks({"cam0": 0.0, "cam1": 0.3, "cam2": 0.6})) == []  # phones started apart: they meet
