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
from dynrecon.names import VIDEO_SUFFIXES
from dynrecon.readers import read_json
from labeling.skeleton import Skeleton, skeleton_from_json
from tracking.workspace import CONFIG_NAME

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class WorkspaceConfig:
    videos: dict[str, Path] = field(default_factory=dict)  # name -> video file
    skeleton: Skeleton = field(default_factory=Skeleton)


def load_config(workspace: Path) -> WorkspaceConfig:
    path = workspace / CONFIG_NAME
    if not path.exists():
        return WorkspaceConfig()
    data = read_json(path, fix="fix or delete the file")
    skeleton = skeleton_from_json(path, data)
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
        if path.is_dir():
            raise InputError(path, "is a folder, not a video file", fix="give the video files themselves to --videos")
        if not path.is_file():
            raise InputError(path, "video file not found", fix="check the path given to --videos")
        name = path.stem
        if name in videos:
            raise InputError(
                path,
                f"two videos are named {name!r} (also {videos[name]})",
                fix="video names are file stems and must be unique: rename one file",
            )
        videos[name] = path.resolve()
    return videos
