"""Synthetic scenes with exact ground truth: a textured static room, moving cameras, moving textured spheres.

`room` renders one view (numpy ray casting, OpenCV texture lookups); `scene` turns camera paths and object
trajectories into videos plus ground-truth `cameras.json`. Used by the SfM tests and benchmarks, and meant to render
a moving subject (spheres at mocap marker positions) for end-to-end samples.
"""

from sfm.synthetic.room import Room, Spheres, render
from sfm.synthetic.scene import CameraPath, SceneVideo, look_at, render_video

__all__ = ["CameraPath", "Room", "SceneVideo", "Spheres", "look_at", "render", "render_video"]
