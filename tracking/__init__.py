"""2D point tracks through every video. Owns `tracks.csv` (`tracking.tracks`) and reads `labels.csv`
(`tracking.labels`), the clicks of the labeling page.

`tracking.track(WS, out, options)` does the whole workspace (`dynrecon track WS`, the stage: `tracking.stage.run`);
`tracking.track_video` carries labels through one in-memory frame source (the labeling page's "track" button).
Everything here loads on first use, so that importing `tracking.tracks` stays cheap (no OpenCV, no tracker).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dynrecon.lazy import lazy_exports

if TYPE_CHECKING:
    from tracking.options import Blend, Method, TrackOptions
    from tracking.propagate import track_video
    from tracking.stage import run as track
    from tracking.tracks import Tracks, read_tracks, write_tracks

__all__ = ["Blend", "Method", "TrackOptions", "Tracks", "read_tracks", "track", "track_video", "write_tracks"]

# public name -> (module, name in that module)
_PUBLIC = {
    "track": ("tracking.stage", "run"),
    "track_video": ("tracking.propagate", "track_video"),
    "TrackOptions": ("tracking.options", "TrackOptions"),
    "Method": ("tracking.options", "Method"),
    "Blend": ("tracking.options", "Blend"),
    "Tracks": ("tracking.tracks", "Tracks"),
    "read_tracks": ("tracking.tracks", "read_tracks"),
    "write_tracks": ("tracking.tracks", "write_tracks"),
}


__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
