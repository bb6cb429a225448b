"""A capture folder: its videos and, optionally, labels or tracks, a calibration, a skeleton and a manifest.

Layout (docs/formats.md, "Capture folder"): the videos (`*.mp4`, `*.mov`, `*.avi`, ...; the file stem is the
video's name), `labels.csv` or `tracks.csv`, `calibration.toml` / `calibration.qca.txt` / `calibration.qca` /
`calibration.xml`, `skeleton.json`, and `capture.json`, a manifest whose keys name other files than the defaults.
Reading a folder checks only what is cheap (files exist, names are unique); decoding is the probe task's job.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES, first_repeated
from dynrecon.readers import check_folder_name, read_json

MANIFEST_NAME = "capture.json"
LABELS_NAME = "labels.csv"
TRACKS_NAME = "tracks.csv"
SKELETON_NAME = "skeleton.json"
CALIBRATION_NAMES = ("calibration.toml", "calibration.qca.txt", "calibration.qca", "calibration.xml")
MANIFEST_KEYS = ("name", "videos", "labels", "tracks", "calibration", "skeleton")


@dataclass(kw_only=True)
class Capture:
    """One capture to reconstruct: absolute paths, so that a worker on another machine finds the same files on the
    shared filesystem."""

    name: str  # the workspace folder's name under the batch's DIR
    folder: Path
    videos: list[Path]
    labels: Path | None = None
    tracks: Path | None = None
    calibration: Path | None = None
    skeleton: Path | None = None
    manifest: dict[str, Any] = field(default_factory=dict)

    @property
    def video_names(self) -> list[str]:
        return [p.stem for p in self.videos]


def read_capture(folder: str | Path) -> Capture:
    """The capture in `folder`; an InputError (one line) when it has no videos or names a file that is absent."""
    folder = Path(folder).resolve()
    if not folder.is_dir():
        raise InputError(folder, "capture folder not found", fix="give folders that hold a capture's videos")
    manifest = _manifest(folder)
    videos = _videos(folder, manifest)
    names = [p.stem for p in videos]
    twice = first_repeated(names)
    if twice is not None:
        raise InputError(folder, f"two videos are named {names[twice]!r}", fix="video file names must differ")
    name = check_folder_name(
        str(manifest.get("name") or folder.name),
        folder / MANIFEST_NAME if manifest.get("name") else folder,
        what="capture name",
        fix="\"name\" names the capture's workspace folder under the batch's --out: give a plain folder name",
    )
    capture = Capture(
        name=name,
        folder=folder,
        videos=videos,
        labels=_optional(folder, manifest, "labels", (LABELS_NAME,)),
        tracks=_optional(folder, manifest, "tracks", (TRACKS_NAME,)),
        calibration=_optional(folder, manifest, "calibration", CALIBRATION_NAMES),
        skeleton=_optional(folder, manifest, "skeleton", (SKELETON_NAME,)),
        manifest=manifest,
    )
    if capture.labels is not None and capture.tracks is not None:
        raise InputError(
            folder, "has both labels and tracks", fix=f"keep {LABELS_NAME} (to track) or {TRACKS_NAME}, not both"
        )
    return capture


def _manifest(folder: Path) -> dict[str, Any]:
    path = folder / MANIFEST_NAME
    if not path.is_file():
        return {}
    document = read_json(path, fix=f"a JSON object with keys {', '.join(MANIFEST_KEYS)}")  # errors: line:column
    if not isinstance(document, dict):
        raise InputError(path, "is not a JSON object", fix=f"keys: {', '.join(MANIFEST_KEYS)}")
    unknown = sorted(set(document) - set(MANIFEST_KEYS))
    if unknown:
        raise InputError(path, f"unknown key {unknown[0]!r}", fix=f"keys: {', '.join(MANIFEST_KEYS)}")
    return document


def _videos(folder: Path, manifest: dict[str, Any]) -> list[Path]:
    listed = manifest.get("videos")
    if listed is not None:
        if not isinstance(listed, list) or not all(isinstance(v, str) for v in listed):
            raise InputError(folder / MANIFEST_NAME, "'videos' must be a list of file names")
        videos = [folder / v for v in listed]
        for video in videos:
            if not video.is_file():
                raise InputError(video, "video not found", fix=f"fix the 'videos' list of {MANIFEST_NAME}")
    else:
        videos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        raise InputError(
            folder, "no videos", fix=f"put the capture's videos ({', '.join(VIDEO_SUFFIXES)}) in the folder"
        )
    return [p.resolve() for p in videos]


def _optional(folder: Path, manifest: dict[str, Any], key: str, defaults: tuple[str, ...]) -> Path | None:
    """The file the manifest names for `key` (which must exist), else the first default name present."""
    named = manifest.get(key)
    if named is not None:
        if not isinstance(named, str):
            raise InputError(folder / MANIFEST_NAME, f"'{key}' must be a file name")
        path = folder / named
        if not path.is_file():
            raise InputError(path, f"{key} file not found", fix=f"fix '{key}' in {MANIFEST_NAME} or add the file")
        return path.resolve()
    return next(((folder / d).resolve() for d in defaults if (folder / d).is_file()), None)
