"""`register`'s matching of people across videos, for tracks that number them per video (`import-tracks --person
all`): which person of one static video is which of another (sfm/subject/people.py), before the background check
and the subject path read the tracks. cameras.json keeps each video's map (`people`), which the solve applies."""

from __future__ import annotations

import logging
from typing import Any

from sfm.people import per_video_people
from sfm.plan import VideoPlan
from sfm.subject.model import SubjectVideo
from sfm.subject.people import PeopleAssociation, associate_people
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def match_people(
    plans: list[VideoPlan], tracks: Tracks | None, warnings: list[str]
) -> tuple[Tracks | None, PeopleAssociation | None, dict[str, Any] | None]:
    """The tracks renumbered across the static videos, the association, and the report's `people` section (None
    when the tracks number no people per video)."""
    people = per_video_people(tracks) if tracks is not None else None
    if tracks is None or people is None:
        return tracks, None, None
    static = [p for p in plans if p.static and p.info.name in people]
    moving = sorted(set(people) - {p.info.name for p in static})
    if moving:
        warnings.append(
            f"people of {', '.join(moving)} (not static cameras) are not matched with other videos' people: their "
            "person<N>_ points keep their own numbers"
        )
    if len(static) < 2:
        why = f"{len(static)} static video(s) have people in their tracks; matching them needs 2"
        warnings.append(f"people: {why}")
        return tracks, None, {"matched": False, "why": why}
    videos = [
        SubjectVideo(name=p.info.name, width=p.info.width, height=p.info.height, times=p.info.times) for p in static
    ]
    found = associate_people(tracks, videos)
    section: dict[str, Any] = {"matched": bool(found.groups), **found.to_json()}
    if not found.groups:
        why = (
            "no person of one video moves consistently with a person of another (one epipolar geometry for their "
            "keypoints); check that the videos film the same people at the same time"
        )
        warnings.append(f"people: {why}")
        section["why"] = why
        return tracks, None, section
    described = "; ".join(
        f"person {n}: " + ", ".join(f"{video} {own}" for video, own in group.items())
        for n, group in enumerate(found.groups)
    )
    log.info("people matched across videos (new number: video's own number): %s", described)
    dropped = {video: own for video, own in found.left_out.items() if own}
    if dropped:
        log.info(
            "people matched with no other video's (left out of the solve): %s",
            "; ".join(f"{video}: {', '.join(map(str, own))}" for video, own in dropped.items()),
        )
    return found.tracks, found, section
