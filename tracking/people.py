"""Who is who across the frames of one video.

A multi-person pose detector lists each frame's people in no fixed order (OpenPose's `people[]`, ordered by its own
scores frame by frame), so entry k of every frame is not one person. Each frame's poses are linked to the identities
seen in the frames before by the least median keypoint displacement (Hungarian assignment), relative to the body's
size; a pose that moved further than a person can between those frames starts a new identity.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError

log = logging.getLogger(__name__)

PERSON = re.compile(r"^person(\d+)_(.+)$")  # a keypoint of person N, as `person_point` names it
MAX_STEP = 0.25  # median keypoint displacement per frame, as a fraction of the body's size, that still links a pose
MAX_JUMP = 1.0  # ... and the most over any gap (a body's size)
MAX_GAP = 30  # frames an identity may go unseen and still be linked
MIN_SIZE_PX = 20.0  # body size floor: a pose of one or two keypoints has no extent


def person_point(person: int, keypoint: str) -> str:
    """The point name of `keypoint` of person `person` (`import-tracks --person all`; as DeepLabCut prefixes its
    individuals' names)."""
    return f"person{person}_{keypoint}"


def tool_name(individual: str, part: str) -> str:
    """A tracker's own name of a point: <individual>_<bodypart>, or the bare bodypart of a scene point ("")."""
    return f"{individual}_{part}" if individual else part


_SAID: set[tuple[str, tuple[str, ...]]] = set()  # the files whose individuals were warned about


def individual_names(
    path: Path,
    detections: dict[tuple[str, str], int],
    person: int | None,
    every_person: bool,
    word: str = "individuals",
) -> dict[tuple[str, str], str | None]:
    """The point names of a tracker's named individuals (DeepLabCut's individuals, SLEAP's tracks), whose identities
    hold within a video only. detections: (individual or "" for a scene point, bodypart) -> its detections, in the
    file's order. Returns each such point -> the name it is imported as, None to leave it out. The individuals are
    numbered by their detections (most first, ties in the file's order), as OpenPose's people are: `person` N keeps
    individual N under the bare bodypart names, `every_person` names each person<N>_<bodypart> (`person_point`), and
    neither keeps the tracker's names (`tool_name`)."""
    points = list(detections)
    seen: dict[str, int] = {}
    for (individual, _), count in detections.items():
        seen[individual] = seen.get(individual, 0) + count
    individuals = list(dict.fromkeys(i for i, _ in points if i))
    if person is None and not every_person:
        present = [i for i in individuals if seen.get(i, 0) > 0]
        said = (str(path), tuple(present))
        if len(present) > 1 and said not in _SAID:  # a file of several videos is read per video: said once
            _SAID.add(said)
            log.warning(
                "%s: %d %s seen (%s): each name is taken as the same animal in every video; where the tracker did "
                "not learn to tell them apart, --person all lets register match them across the videos from their "
                "motion",
                path.name,
                len(present),
                word,
                ", ".join(present),
            )
        return _unique(path, {(i, part): tool_name(i, part) for i, part in points})
    if not individuals:  # one unnamed subject, as OpenPose's single person: person 0
        if person not in (None, 0):
            raise InputError(path, f"--person {person}, but the file names no {word}", fix="leave --person out")
        return _unique(path, {(i, part): person_point(0, part) if every_person else part for i, part in points})
    ranked = sorted(individuals, key=lambda i: -seen.get(i, 0))  # stable: ties keep the file's order
    number = {i: n for n, i in enumerate(ranked)}
    log.info(
        "%s: %s by how much they are seen: %s",
        path.name,
        word,
        ", ".join(f"{n} = {i} ({seen.get(i, 0)} detections)" for n, i in enumerate(ranked)),
    )
    if not every_person and person is not None and person >= len(ranked):
        raise InputError(
            path,
            f"--person {person}, but the file has {len(ranked)} {word} ({', '.join(individuals)})",
            fix=f"give a number below {len(ranked)}, or --person all",
        )
    names: dict[tuple[str, str], str | None] = {}
    for i, part in points:
        if not i:  # a scene point (DLC's `single` unique bodyparts): one per video
            names[i, part] = part
        elif every_person:
            names[i, part] = person_point(number[i], part)
        else:
            names[i, part] = part if number[i] == person else None
    return _unique(path, names)


def _unique(path: Path, names: dict[tuple[str, str], str | None]) -> dict[tuple[str, str], str | None]:
    """`names`, unless two points would be imported under one name (a scene point named as an animal's bodypart)."""
    owner: dict[str, tuple[str, str]] = {}
    for key, name in names.items():
        if name is None:
            continue
        if name in owner:
            first, second = (tool_name(*k) for k in (owner[name], key))
            raise InputError(
                path, f"{first} and {second} would both be imported as {name!r}", fix="rename one with --map first"
            )
        owner[name] = key
    return names


@dataclass(kw_only=True)
class Identity:
    """One person as linked through a video's frames."""

    frames: int  # frames it is seen in
    keypoints: int  # confident keypoints in all those frames
    first: int  # first frame seen


def link_people(poses: list[tuple[int, list[np.ndarray]]]) -> tuple[list[list[int]], list[Identity]]:
    """poses: per frame (increasing), (frame, [(K, 3) x, y, confidence per person; confidence 0 = not seen]) ->
    the identity of each person of each frame, and the identities, numbered by confident keypoints (most first,
    so 0 is the person seen most)."""
    from scipy.optimize import linear_sum_assignment  # here: `dynrecon track --help` must not load scipy

    last: list[tuple[int, np.ndarray]] = []  # per raw identity: (frame last seen, its pose there)
    counts: list[list[int]] = []  # per raw identity: frames, keypoints, first frame
    raw: list[list[int]] = []
    for frame, people in poses:
        active = [i for i, (seen, _) in enumerate(last) if frame - seen <= MAX_GAP]
        assigned = [-1] * len(people)
        if active and people:
            # not divided by the gap: an identity unseen for longer must not win a pose from one seen just before
            cost = np.array([[_step(last[i][1], pose) for pose in people] for i in active])
            limits = np.array([min(MAX_STEP * (frame - last[i][0]), MAX_JUMP) for i in active])
            rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] <= limits[r]:
                    assigned[c] = active[r]
        for c, pose in enumerate(people):
            if assigned[c] < 0:
                assigned[c] = len(last)
                last.append((frame, pose))
                counts.append([0, 0, frame])
            identity = assigned[c]
            # keypoints this pose misses keep their last position: a partial pose keeps the body's size and shape
            merged = last[identity][1].copy()
            seen = pose[:, 2] > 0
            merged[seen] = pose[seen]
            last[identity] = (frame, merged)
            counts[identity][0] += 1
            counts[identity][1] += int((pose[:, 2] > 0).sum())
        raw.append(assigned)
    order = sorted(range(len(counts)), key=lambda i: (-counts[i][1], counts[i][2]))
    number = {old: new for new, old in enumerate(order)}
    identities = [Identity(frames=counts[i][0], keypoints=counts[i][1], first=counts[i][2]) for i in order]
    return [[number[i] for i in frame] for frame in raw], identities


def _step(a: np.ndarray, b: np.ndarray) -> float:
    """Median displacement (in a's body sizes) of the keypoints seen in both poses (their centroids when none is)."""
    seen_a, seen_b = a[:, 2] > 0, b[:, 2] > 0
    if not seen_a.any() or not seen_b.any():
        return np.inf
    both = seen_a & seen_b
    if both.any():
        distance = float(np.median(np.linalg.norm(a[both, :2] - b[both, :2], axis=1)))
    else:
        distance = float(np.linalg.norm(a[seen_a, :2].mean(axis=0) - b[seen_b, :2].mean(axis=0)))
    extent = a[seen_a, :2].max(axis=0) - a[seen_a, :2].min(axis=0)
    return distance / max(float(np.linalg.norm(extent)), MIN_SIZE_PX)
