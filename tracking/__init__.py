"""2D point tracks through every video. Owns the `tracks.csv` contract (`tracking.tracks`).

`tracking.propagate.track_video` carries labels through one in-memory frame source (the labeling page's
"track" button); `tracking.run` does the whole workspace (`dynrecon track WS`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tracking.options import TrackOptions


def run(workspace: str | Path, out: str | Path | None = None, options: TrackOptions | None = None, *,
        videos: dict[str, Path] | list[Path] | None = None) -> Path:
    """`tracking.stage.run`; imported late so that `tracking.tracks` stays cheap to import."""
    from tracking.stage import run as run_stage

    return run_stage(workspace, out, options, videos=videos)
