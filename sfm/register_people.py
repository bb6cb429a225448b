"""`register`'s matching of people across videos, for tracks that number them per video (`import-tracks --person
all`): which person of one static video is which of another (sfm/subject/people.py), before the background check
and the subject path read the tracks. cameras.json keeps each video's map (`people`), which the solve applies."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from sfm.cameras import read_cameras, write_cameras
from sfm.options import MAX_OFFSET_S
from sfm.people import per_video_people, renumber_people
from sfm.plan import VideoPlan
from sfm.register_check import static_times
from sfm.subject.model import SubjectVideo
from sfm.subject.people import associate_people
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def match_people(
    plans: list[VideoPlan], tracks: Tracks | None, warnings: list[str], max_offset: float = MAX_OFFSET_S
) -> tuple[Tracks | None, dict[str, dict[int, int]], dict[str, Any] | None]:
    """The tracks renumbered across the static videos, each video's map (own number -> number across videos; every
    video with people gets one, so that people matched with nobody, and those of moving videos, leave the solve as
    they leave registration), and the report's `people` section (None when the tracks number no people per
    video)."""
    people = per_video_people(tracks) if tracks is not None else None
    if tracks is None or people is None:
        return tracks, {}, None
    static = [p for p in plans if p.static and p.info.name in people]
    moving = sorted(set(people) - {p.info.name for p in static})
    if moving:
        warnings.append(
            f"people: {', '.join(moving)} (not static cameras) cannot be matched with other videos' people; their "
            "person<N>_ points are left out"
        )
    maps: dict[str, dict[int, int]] = {}
    section: dict[str, Any]
    if len(static) < 2:
        section = {
            "matched": False,
            "why": f"{len(static)} static video(s) have people in their tracks; matching them needs 2",
        }
    else:
        videos = [
            SubjectVideo(name=p.info.name, width=p.info.width, height=p.info.height, times=p.info.times) for p in static
        ]
        found = associate_people(tracks, videos, max_offset=max_offset)
        maps = found.maps
        section = {"matched": bool(found.groups), **found.to_json()}
        if found.groups:
            described = "; ".join(
                f"person {n}: " + ", ".join(f"{video} {own}" for video, own in group.items())
                for n, group in enumerate(found.groups)
            )
            log.info("people matched across videos (new number: video's own number): %s", described)
            dropped = {video: own for video, own in found.left_out.items() if own}
            if dropped:
                log.info(
                    "people matched with no other video's (left out): %s",
                    "; ".join(f"{video}: {', '.join(map(str, own))}" for video, own in dropped.items()),
                )
        else:
            section["why"] = (
                "no person of one video moves consistently with a person of another (one epipolar geometry for "
                "their keypoints); check that the videos film the same people at the same time"
            )
    if not section["matched"]:
        warnings.append(f"people: {section['why']}; the person<N>_ points are left out")
    for name in people:
        maps.setdefault(name, {})
    return renumber_people(tracks, maps), maps, section


def people_on_cameras(cameras_path: Path, tracks: Tracks, videos: list[Path], out: Path) -> Path:
    """Fixed cameras (a lab's calibration, imported without tracks) with each video's people map, found from
    `tracks` as `register` finds it: cameras.json written into `out` (and returned)."""
    cameras = read_cameras(cameras_path)
    people = per_video_people(tracks) or {}
    paths = {p.stem: p for p in videos}
    inputs = []
    for video in cameras.videos:
        if video.name not in people or not video.frames:
            continue
        own = static_times(video, paths.get(video.name))
        inputs.append(SubjectVideo(name=video.name, width=video.width, height=video.height, times=own))
    maps = associate_people(tracks, inputs).maps if len(inputs) >= 2 else {}
    if not any(maps.values()):
        log.warning("people: no person of one video is matched with a person of another; their points are left out")
    for video in cameras.videos:
        video.people = maps.get(video.name, {}) if video.name in people else None
    return write_cameras(out / "cameras.json", cameras)
