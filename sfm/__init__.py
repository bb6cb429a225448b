"""Camera registration: a pose and intrinsics for every frame of every video, in one world frame.

Owns the `cameras.json` contract (`sfm.cameras`).
"""
