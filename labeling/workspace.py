"""Workspace settings of the labeling page: which videos, which named points, which connections.

`WS/labeling.json` (see docs/formats.md) remembers them between sessions:
    {"videos": {"cam01": "videos/cam01.mp4"}, "points": ["head", "hip"], "connections": [["head", "hip"]]}
(video paths relative to WS, or absolute)
Videos are named by file stem; that name is the `video` column of labels.csv and tracks.csv.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import InputError
from dynrecon.readers import read_json, shown

log = logging.getLogger(__name__)

CONFIG_NAME = "labeling.json"
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")


@dataclass(kw_only=True)
class Skeleton:
    """Named points in display order and the pairs drawn as lines between them."""

    points: list[str] = field(default_factory=list)
    connections: list[tuple[str, str]] = field(default_factory=list)

    def add_point(self, name: str) -> None:
        if name not in self.points:
            self.points.append(name)

    def merge(self, other: Skeleton) -> None:
        for name in other.points:
            self.add_point(name)
        for pair in other.connections:
            if pair not in self.connections and pair[::-1] not in self.connections:
                self.connections.append(pair)

    def rename(self, old: str, new: str) -> None:
        self.points = [new if p == old else p for p in self.points]
        self.connections = [(new if a == old else a, new if b == old else b) for a, b in self.connections]


def valid_point_name(name: str) -> bool:
    """Names go into CSV cells and the page; keep them printable, short and free of separators."""
    return bool(name) and len(name) <= 64 and name == name.strip() and name.isprintable() \
        and not any(c in name for c in ',"\'\\/<>')


def parse_points(text: str) -> Skeleton:
    """`--points a,b,c`."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if not valid_point_name(n)]
    if bad:
        raise InputError(None, f"--points: invalid point name {bad[0]!r}",
                         fix="names are up to 64 printable characters without , \" ' \\ / < >")
    return Skeleton(points=list(dict.fromkeys(names)))


def read_skeleton(path: Path) -> Skeleton:
    """Skeleton JSON `{"points": [...], "connections": [["a", "b"], ...]}`; connections may add points."""
    data = read_json(path, missing_fix="give the path of a skeleton JSON file")
    return _skeleton_from_json(path, data)


def _skeleton_from_json(path: Path, data: object) -> Skeleton:
    fix = 'expected {"points": ["a", "b"], "connections": [["a", "b"]]}'
    if not isinstance(data, dict):
        raise InputError(path, "top level is not an object", fix=fix)
    points = data.get("points", [])
    connections = data.get("connections", [])
    if not isinstance(points, list) or not all(isinstance(p, str) and valid_point_name(p) for p in points):
        raise InputError(path, "'points' must be a list of point names", fix=fix)
    skeleton = Skeleton(points=list(dict.fromkeys(points)))
    if not isinstance(connections, list):
        raise InputError(path, "'connections' must be a list of pairs", fix=fix)
    for i, pair in enumerate(connections):
        if not (isinstance(pair, list | tuple) and len(pair) == 2
                and all(isinstance(p, str) and valid_point_name(p) for p in pair)) or pair[0] == pair[1]:
            raise InputError(path, f"connection {i} ({shown(pair)}) is not a pair of two different point names",
                             fix=fix)
        skeleton.add_point(pair[0])
        skeleton.add_point(pair[1])
        skeleton.connections.append((pair[0], pair[1]))
    return skeleton


@dataclass(kw_only=True)
class WorkspaceConfig:
    videos: dict[str, Path] = field(default_factory=dict)  # name -> video file
    skeleton: Skeleton = field(default_factory=Skeleton)


def load_config(workspace: Path) -> WorkspaceConfig:
    path = workspace / CONFIG_NAME
    if not path.exists():
        return WorkspaceConfig()
    data = read_json(path, fix="fix or delete the file")
    skeleton = _skeleton_from_json(path, data)
    videos_raw = data.get("videos", {})
    if not isinstance(videos_raw, dict) or not all(isinstance(v, str) for v in videos_raw.values()):
        raise InputError(path, "'videos' must map video names to file paths", fix="fix or delete the file")
    videos = {name: (Path(p) if Path(p).is_absolute() else workspace / p) for name, p in videos_raw.items()}
    return WorkspaceConfig(videos=videos, skeleton=skeleton)


def save_config(workspace: Path, config: WorkspaceConfig) -> None:
    def show(p: Path) -> str:
        # Paths inside the workspace stay relative so the workspace can be moved as a whole.
        try:
            return str(p.resolve().relative_to(workspace.resolve()))
        except ValueError:
            return str(p.resolve())

    data = {
        "videos": {name: show(p) for name, p in config.videos.items()},
        "points": config.skeleton.points,
        "connections": [list(pair) for pair in config.skeleton.connections],
    }
    atomic_write_text(workspace / CONFIG_NAME, json.dumps(data, indent=2) + "\n")


def resolve_videos(workspace: Path, given: list[Path] | None, remembered: dict[str, Path]) -> dict[str, Path]:
    """Videos named by stem: the given files, else those remembered in labeling.json, else `WS/videos/*`."""
    if given:
        files = list(given)
    elif remembered:
        files = list(remembered.values())
    else:
        folder = workspace / "videos"
        files = sorted(p for p in folder.glob("*") if p.suffix.lower() in VIDEO_SUFFIXES)
    if not files:
        raise InputError(workspace, "no videos", fix="pass --videos V1 V2 ... or put them in WS/videos/")
    videos: dict[str, Path] = {}
    for path in files:
        if not path.is_file():
            raise InputError(path, "video file not found", fix="check the path given to --videos")
        name = path.stem
        if name in videos:
            raise InputError(path, f"two videos are named {name!r} (also {videos[name]})",
                             fix="video names are file stems and must be unique: rename one file")
        videos[name] = path.resolve()
    return videos
