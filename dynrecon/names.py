"""Video names: the file suffixes read as videos, and the key that matches names spelled differently."""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv")


def video_name(value: str | Path) -> str:
    """The video a command-line value names: a video file by its stem, as the videos' own names are; else the
    value's last part (a name such as cam0)."""
    path = Path(value)
    return path.stem if path.suffix.lower() in VIDEO_SUFFIXES else path.name


def name_key(name: str) -> str:
    """'Cam_01.mp4', 'cam01', 'cam-1' all become 'cam-1': tools and users spell a video's name differently (case,
    separators, leading zeros, a file suffix). Its words and numbers stay apart: 'cam1_2' is not 'cam12'."""
    name = name.lower()
    for suffix in VIDEO_SUFFIXES:
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return "-".join(str(int(t)) if t.isdigit() else t for t in re.findall(r"[^\W\d_]+|\d+", name))


def first_repeated(names: Iterable[str]) -> int | None:
    """The index of the first name that an earlier one repeats, None when all differ."""
    seen: set[str] = set()
    for i, name in enumerate(names):
        if name in seen:
            return i
        seen.add(name)
    return None


def spelled_alike(name: str, names: Iterable[str]) -> list[str]:
    """[`name`] when it is among `names`, else those of `names` with its key: one is a match, several ambiguous."""
    names = list(names)
    return [name] if name in names else [n for n in names if name_key(n) == name_key(name)]


def within_name(name: str, names: Iterable[str]) -> list[str]:
    """Those of `names` whose key's words and numbers begin or end `name`'s: a session's prefix or a take's suffix
    around a camera's name ('minimal_back' holds 'back', 'cam01_take2' holds 'cam_1'); one is a match. A name of
    numbers only matches nothing this way ('cam1_take2' must not be camera '2')."""
    words = name_key(name).split("-")
    found = []
    for other in names:
        own = name_key(other).split("-")
        if all(w.isdigit() or not w for w in own) or len(own) >= len(words):
            continue
        if words[: len(own)] == own or words[-len(own) :] == own:
            found.append(other)
    return found


def numbered_name(name: str, names: Iterable[str]) -> list[str]:
    """Those of `names` that are a number alone, the number `name` ends on after one word ('cam10' for anipose's
    camera '10'); one is a match. Only for a name of one word and one number: 'cam1_take2' is not camera '2'."""
    words = name_key(name).split("-")
    if len(words) != 2 or not words[0].isalpha() or not words[1].isdigit():
        return []
    return [other for other in names if name_key(other) == words[1]]


def holds_name(name: str, names: Iterable[str]) -> list[str]:
    """Those of `names` whose key's words and numbers hold `name`'s as one whole run, anywhere: a calibration's
    camera named around the video's ('int_cam01_img' holds 'cam01', Pose2Sim's intrinsics-board cameras); one is a
    match. A name of numbers only matches nothing this way."""
    words = name_key(name).split("-")
    if all(w.isdigit() or not w for w in words):
        return []
    found = []
    for other in names:
        own = name_key(other).split("-")
        runs = (own[i : i + len(words)] for i in range(len(own) - len(words) + 1))
        if len(own) > len(words) and any(run == words for run in runs):
            found.append(other)
    return found
