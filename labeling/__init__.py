"""Manual keypoint labeling in a local web page: `labeling.label(WS, options)` serves it until interrupted.

The page writes `WS/labels.csv` (format: `tracking.labels`) and runs the tracker (`tracking.track`); the skeleton
file (named points and connections) is `labeling.skeleton`. Everything here loads on first use, so that importing a
light module such as `labeling.skeleton` does not load the server and OpenCV.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dynrecon.lazy import lazy_exports

if TYPE_CHECKING:
    from labeling.skeleton import Skeleton, read_skeleton
    from labeling.stage import LabelOptions, LabelServer
    from labeling.stage import run as label

__all__ = ["LabelOptions", "LabelServer", "Skeleton", "label", "read_skeleton"]

# public name -> (module, name in that module)
_PUBLIC = {
    "label": ("labeling.stage", "run"),
    "LabelOptions": ("labeling.stage", "LabelOptions"),
    "LabelServer": ("labeling.stage", "LabelServer"),
    "Skeleton": ("labeling.skeleton", "Skeleton"),
    "read_skeleton": ("labeling.skeleton", "read_skeleton"),
}


__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
