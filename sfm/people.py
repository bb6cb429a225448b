"""People numbered per video (`import-tracks --person all`: points `person<N>_<keypoint>`) renumbered across videos.

`register` finds which person of one video is which of another (sfm/subject/people.py) and writes each video's
map into cameras.json (`people`); the solve renumbers the tracks with it, so that one person's keypoints carry one
name in every video. tracks.csv keeps the detector's own numbers.
"""

from __future__ import annotations

import re

import numpy as np

from sfm.cameras import CameraSet
from tracking.tracks import Tracks

PERSON = re.compile(r"^person(\d+)_(.+)$")


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
            point[i] = f"person{new}_{match.group(2)}"
    index = np.flatnonzero(keep)
    out = tracks.take(index)
    out.point = [point[i] for i in index]
    return out
