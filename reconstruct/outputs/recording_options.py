"""What a caller may choose about the rerun recording, importable without rerun (`reconstruct.outputs.recording`
draws it)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class WorldAxes(Enum):
    """How the world's axes map to the viewer's up direction."""

    Y_DOWN = "y_down"  # COLMAP / OpenCV reconstructions (the cameras' y points down)
    Z_UP = "z_up"  # motion capture and OpenSim-style worlds
    Y_UP = "y_up"


@dataclass(kw_only=True)
class RecordingOptions:
    """world_axes: which way is up in the viewer. blueprint: save the default layout (a 3D view, one 2D view per
    camera, the residual plot) with the recording; without it the viewer picks its own."""

    world_axes: WorldAxes = WorldAxes.Y_DOWN
    blueprint: bool = True
