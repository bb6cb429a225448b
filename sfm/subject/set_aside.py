"""The largest group of videos whose tracks determine their cameras: set aside the video that spoils the others.

One video whose tracks follow another person (a detector that switched subjects) or nothing at all pulls every
camera of a joint bundle adjustment: the folds of `check_stability` then find none of them determined, and the
path poses nothing, though the other videos pose each other well. Each round sets aside the least determined
video (the largest fold change, in units of the stability limits) and solves the rest again; a smaller group is
kept only where it leaves more cameras determined, so a rig where all videos but one are determined is solved
once and unchanged.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection
from typing import TypeVar

from sfm.subject.model import SubjectCalibrationError, SubjectResult, SubjectVideo
from sfm.subject.noise import stable_cameras
from sfm.subject.stability import MAX_CENTRE, MAX_ROTATION_DEG, Stability, pair_without_intrinsics

log = logging.getLogger(__name__)

T = TypeVar("T")
MAX_ROUNDS = 3  # videos set aside at most (each round is a whole solve with its folds)


def largest_determined(
    trial: Callable[[list[SubjectVideo]], tuple[SubjectResult, Stability, T]],
    videos: list[SubjectVideo],
    keep: Collection[str] = (),
) -> tuple[SubjectResult, Stability, T]:
    """`trial` (the subject path on some of `videos`, with its folds) on all of them, then without its least
    determined video while some camera is not determined and at least three videos would remain (two with known
    intrinsics); `keep` (videos the background posed) are never set aside. A video set aside is in the returned
    result's `failed`, with why, and in its `set_aside`."""
    best = trial(videos)
    if _settled(best[0], best[1]):
        return best
    group = list(videos)
    aside: dict[str, str] = {}
    kept_aside: dict[str, str] = {}
    current = best
    for _ in range(MAX_ROUNDS):
        result, stability = current[0], current[1]
        candidates = [c.name for c in result.cameras if c.name in stability.unstable and c.name not in keep]
        # a smaller group is kept only where it determines more cameras: none can once all but one are
        if not candidates or len(group) <= 2 or len(stable_cameras(best[0], best[1])) >= len(group) - 1:
            break
        worst = max(candidates, key=lambda n: _change(stability, n))
        rest = [v for v in group if v.name != worst]
        if pair_without_intrinsics(rest):  # refused by its folds' check whatever they show: no solve for it
            break
        group = rest
        aside[worst] = stability.unstable[worst]
        try:
            current = trial(group)
        except SubjectCalibrationError as error:
            log.info("subject path without %s: %s", ", ".join(aside), error)
            break
        if _better(current, best):
            best, kept_aside = current, dict(aside)
        if _settled(current[0], current[1]):
            break
    if kept_aside:
        determined = stable_cameras(best[0], best[1])
        log.info("subject path: set aside %s; the others pose %s", ", ".join(kept_aside), ", ".join(determined))
        best[0].set_aside = list(kept_aside)
        without = ", ".join(kept_aside)
        for name, why in kept_aside.items():
            best[0].failed[name] = (
                f"set aside: solved with the other videos, its camera was {why.split('; ')[0]}; without {without}, "
                f"{len(determined)} camera(s) are determined ({', '.join(determined)}): check that its tracks follow "
                "the same subject as the other videos', and that it sees enough of the subject"
            )
    return best


def _settled(result: SubjectResult, stability: Stability) -> bool:
    return not any(c.name in stability.unstable for c in result.cameras)


def _change(stability: Stability, name: str) -> float:
    """The camera's largest fold change in units of the stability limits (inf where no fold posed it)."""
    centre, rotation = stability.centre.get(name), stability.rotation_deg.get(name)
    if centre is None and rotation is None:
        return float("inf")
    return max((centre or 0.0) / MAX_CENTRE, (rotation or 0.0) / MAX_ROTATION_DEG)


def _better(new: tuple[SubjectResult, Stability, object], old: tuple[SubjectResult, Stability, object]) -> bool:
    """More cameras determined, among them every one the larger group determined (as many: the larger group's
    poses are kept, its every video's evidence in them)."""
    stable_new, stable_old = stable_cameras(new[0], new[1]), stable_cameras(old[0], old[1])
    kept = {c.name for c in new[0].cameras} | set(new[0].failed)
    return len(stable_new) > len(stable_old) and set(stable_old) & kept <= set(stable_new)


__all__ = ["MAX_ROUNDS", "largest_determined"]
