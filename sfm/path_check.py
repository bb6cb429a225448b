"""A moving camera's poses along its video: a frame whose pose jumps off the path its neighbours agree on, on
weak support, is no camera's (a keyframe held in the model by two observations put a handheld phone 1,231 units
from its path, a fast pan's keyframe of 47 observations turned 35 deg and back within two frames), and is left
unposed with a warning naming it. A jump the frame's own matches support as well as its neighbours' (a camera
truly jerked) is kept."""

from __future__ import annotations

import numpy as np

from sfm.plan import FramePose, VideoPlan

SPIKE_RATIO = 5.0  # a frame this many times farther from its neighbours' midpoint than they lie apart (or than
# the video's median step) ...
SPIKE_DEG = 10.0  # ... or turned at least this much from both neighbours, and 3x their own turn and the median one
SPIKE_TURNS = 3.0
WEAK_SHARE = 0.5  # a jump counts when its frame's inliers are under this share of the video's median

Results = dict[str, dict[int, FramePose]]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a @ b.T) - 1.0) / 2.0, -1.0, 1.0))))


def path_spikes(centres: np.ndarray, rotations: np.ndarray) -> list[int]:
    """Indices (into the posed frames, in frame order) of the poses that jump off their neighbours' path: centres
    (N, 3), cam_from_world rotations (N, 3, 3)."""
    if len(centres) < 3:
        return []
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    turns = np.array([_angle_deg(rotations[i], rotations[i + 1]) for i in range(len(rotations) - 1)])
    step, turn = float(np.median(steps)), float(np.median(turns))
    spikes = []
    for i in range(1, len(centres) - 1):
        a, f, b = centres[i - 1], centres[i], centres[i + 1]
        apart = float(np.linalg.norm(b - a))
        off = float(np.linalg.norm(f - 0.5 * (a + b)))
        own = _angle_deg(rotations[i - 1], rotations[i + 1])
        turned = min(_angle_deg(rotations[i], rotations[i - 1]), _angle_deg(rotations[i], rotations[i + 1]))
        jumps = off > SPIKE_RATIO * max(apart, step) and off > 0
        turns_away = turned > max(SPIKE_DEG, SPIKE_TURNS * own, SPIKE_TURNS * turn)
        if jumps or turns_away:
            spikes.append(i)
    return spikes


def drop_spikes(plans: list[VideoPlan], results: Results, warnings: list[str]) -> None:
    """Unpose the background poses of moving videos that jump off their path (`path_spikes`), one warning per
    video naming the frames."""
    for plan in plans:
        if plan.static:
            continue
        name = plan.info.name
        frames = results[name]
        posed = sorted(f for f, r in frames.items() if r.pose is not None and r.source != "subject")
        if len(posed) < 3:
            continue
        poses = [frames[f].pose for f in posed]
        rotations = np.array([p.rotation.matrix() for p in poses if p is not None])
        centres = np.array(
            [-R.T @ np.asarray(p.translation) for R, p in zip(rotations, poses, strict=True) if p is not None]
        )
        support = np.array([frames[f].inliers if frames[f].inliers is not None else np.inf for f in posed], float)
        finite = support[np.isfinite(support)]
        weak = WEAK_SHARE * float(np.median(finite)) if finite.size else 0.0
        spikes = [posed[i] for i in path_spikes(centres, rotations) if support[i] < weak]
        if not spikes:
            continue
        for frame in spikes:
            frames[frame] = FramePose(
                pose=None, reason="its pose jumps off the path of its neighbouring frames (a false model pose)"
            )
        shown = ", ".join(map(str, spikes[:8])) + (f" and {len(spikes) - 8} more" if len(spikes) > 8 else "")
        warnings.append(
            f"{name}: frame(s) {shown} left unposed: each pose jumped off the path its neighbouring frames agree on "
            f"(over {SPIKE_RATIO:g}x their distance, or turned over {SPIKE_DEG:g} deg from both) on under "
            f"{WEAK_SHARE:.0%} of the video's median inliers"
        )
