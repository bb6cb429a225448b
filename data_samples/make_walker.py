"""Generate `walker.trc`: a procedural walking stick figure (18 joints, 120 Hz, 2 s), made by project code.

Forward kinematics of a simple human: pelvis moving forward with a vertical bob, legs and arms swinging in
opposite phase, knees and elbows bending during the swing. Smooth and periodic like real gait, which is the hard
case for the solver's initialization (similar poses recur every step). Run from the repo root:

    python data_samples/make_walker.py
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from reconstruct.outputs.mocap import Mocap, write_trc

RATE = 120.0
DURATION = 2.0
JOINTS = [
    "pelvis",
    "spine",
    "neck",
    "head",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
    "l_hip",
    "l_knee",
    "l_ankle",
    "l_toe",
    "r_hip",
    "r_knee",
    "r_ankle",
    "r_toe",
]
# Pairs of joints drawn as the skeleton (see walker_skeleton.json).
BONES = [
    ("pelvis", "spine"),
    ("spine", "neck"),
    ("neck", "head"),
    ("neck", "l_shoulder"),
    ("l_shoulder", "l_elbow"),
    ("l_elbow", "l_wrist"),
    ("neck", "r_shoulder"),
    ("r_shoulder", "r_elbow"),
    ("r_elbow", "r_wrist"),
    ("pelvis", "l_hip"),
    ("l_hip", "l_knee"),
    ("l_knee", "l_ankle"),
    ("l_ankle", "l_toe"),
    ("pelvis", "r_hip"),
    ("r_hip", "r_knee"),
    ("r_knee", "r_ankle"),
    ("r_ankle", "r_toe"),
]


def _limb(root: np.ndarray, angles: np.ndarray, lengths: list[float]) -> list[np.ndarray]:
    """Chain of segments hanging from `root` in the sagittal (x-z) plane; angles (T, n) from straight down."""
    points, current, total = [], root, np.zeros(len(root))
    for k, length in enumerate(lengths):
        total = total + angles[:, k]
        current = current + length * np.stack([np.sin(total), np.zeros_like(total), -np.cos(total)], axis=1)
        points.append(current)
    return points


def walker(rate: float = RATE, duration: float = DURATION) -> np.ndarray:
    """(T, 18, 3) joint positions in mm, z up."""
    t = np.arange(int(rate * duration)) / rate
    phase = 2 * np.pi * 0.9 * t  # ~0.9 strides per second
    pelvis = np.stack([1100.0 * t - 1100.0, 20.0 * np.sin(phase), 950.0 + 25.0 * np.cos(2 * phase)], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    spine = pelvis + 250.0 * up
    neck = spine + 250.0 * up + np.stack([30.0 * np.sin(phase), np.zeros_like(t), np.zeros_like(t)], axis=1)
    head = neck + 200.0 * up
    joints = {"pelvis": pelvis, "spine": spine, "neck": neck, "head": head}
    for side, sign in (("l", 1.0), ("r", -1.0)):
        lateral = np.array([0.0, sign * 180.0, 0.0])
        swing = sign * np.sin(phase)
        shoulder = neck + lateral
        elbow, wrist = _limb(
            shoulder, np.stack([-0.5 * swing, 0.3 + 0.25 * np.maximum(-swing, 0)], axis=1), [290.0, 260.0]
        )
        hip = pelvis + 0.55 * lateral
        bend = 0.9 * np.maximum(np.sin(phase * sign + 0.8), 0.0)
        knee, ankle, toe = _limb(
            hip, np.stack([0.45 * swing, -bend, np.full_like(t, 1.45) + 0.3 * bend], axis=1), [430.0, 420.0, 150.0]
        )
        joints.update(
            {
                f"{side}_shoulder": shoulder,
                f"{side}_elbow": elbow,
                f"{side}_wrist": wrist,
                f"{side}_hip": hip,
                f"{side}_knee": knee,
                f"{side}_ankle": ankle,
                f"{side}_toe": toe,
            }
        )
    return np.stack([joints[name] for name in JOINTS], axis=1)


def main() -> None:
    here = Path(__file__).resolve().parent
    xyz = walker()
    mocap = Mocap(xyz=xyz, rate=RATE, marker_names=list(JOINTS), times=np.arange(len(xyz)) / RATE)
    write_trc(here / "walker.trc", mocap)
    (here / "walker_skeleton.json").write_text(json.dumps({"points": JOINTS, "connections": BONES}, indent=1) + "\n")


if __name__ == "__main__":
    main()
