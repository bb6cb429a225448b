"""People numbered per video (`import-tracks --person all`: points `person<N>_<keypoint>`) renumbered across videos.

`register` finds which person of one video is which of another (sfm/subject/people.py) and writes each video's
map into cameras.json (`people`); the solve renumbers the tracks with it, so that one person's keypoints carry one
name in every video. tracks.csv keeps the detector's own numbers. Tracks that number people per video without a
map for each such video are refused (`check_people_mapped`): their names would join different people.
"""

from __future__ import annotations

import numpy as np

from dynrecon.errors import InputError
from sfm.cameras import CameraSet
from tracking.people import PERSON, person_point
from tracking.tracks import Tracks


def per_video_people(tracks: Tracks) -> dict[str, list[int]] | None:
    """Each video's people (`person<N>_<keypoint>` points), when some video has two or more or the videos number
    their one person differently (a threshold can leave another person than the first); else None: one name per
    person, as one subject's tracks."""
    people: dict[str, set[int]] = {}
    for video, point in zip(tracks.video, tracks.point, strict=True):
        match = PERSON.match(point)
        if match:
            people.setdefault(video, set()).add(int(match.group(1)))
    if len({frozenset(p) for p in people.values()}) <= 1 and all(len(p) == 1 for p in people.values()):
        return None
    return {video: sorted(p) for video, p in people.items()}


def people_maps(cameras: CameraSet) -> dict[str, dict[int, int]]:
    """Per video with a map in cameras.json: its own person numbers -> the numbers across videos."""
    return {v.name: v.people for v in cameras.videos if v.people is not None}


def renumber_people(tracks: Tracks, maps: dict[str, dict[int, int]]) -> Tracks:
    """`tracks` with the `person<N>_` points of the mapped videos renumbered; a person of a mapped video that no
    other video's matched (absent from its map) is left out: seen by one camera, it cannot be triangulated."""
    if not maps:
        return tracks
    keep = np.ones(len(tracks), dtype=bool)
    point = list(tracks.point)
    for i, (video, name) in enumerate(zip(tracks.video, tracks.point, strict=True)):
        table = maps.get(video)
        match = PERSON.match(name) if table is not None else None
        if table is None or match is None:
            continue
        new = table.get(int(match.group(1)))
        if new is None:
            keep[i] = False
        else:
            point[i] = person_point(new, match.group(2))
    index = np.flatnonzero(keep)
    out = tracks.take(index)
    out.point = [point[i] for i in index]
    return out


def check_people_mapped(cameras: CameraSet, tracks: Tracks) -> None:
    """Raise InputError when `tracks` number people per video and cameras.json has no map for some of those videos
    (registered without these tracks, or imported from a lab's calibration)."""
    people = per_video_people(tracks)
    if people is None:
        return
    maps = people_maps(cameras)
    posed = {v.name for v in cameras.videos}
    unmapped = sorted(v for v in people if v in posed and v not in maps)
    if unmapped:
        raise InputError(
            tracks.path,
            f"the tracks number people per video (person<N>_<keypoint> points, several people in "
            f"{', '.join(v for v in people if len(people[v]) > 1)}), but cameras.json does not say which person of "
            f"{', '.join(unmapped)} is which of the other videos",
            fix="register with these tracks (dynrecon register VIDEO... --tracks tracks.csv), which matches the "
            "people across the videos; or import one person per video (import-tracks --person N); or rename the "
            "points if their numbers already match across the videos",
        )
