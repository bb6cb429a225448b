"""dynrecon: 3D trajectories of moving points from unsynchronized videos.

The stages live in the top-level packages `sfm`, `tracking`, `labeling` and `reconstruct`; this package holds what
they share (user-facing errors) and the command-line interface on top of them.
"""

__version__ = "0.1.0"
