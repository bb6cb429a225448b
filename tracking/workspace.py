"""What `dynrecon track WS` reads from a labeling workspace: the videos and the manual labels.

Layout (shared with `labeling`):
- `WS/labeling.json`: `{"videos": {"cam01": "videos/cam01.mp4", ...}, ...}`, paths relative to WS or absolute;
  without it, `WS/videos/*` named by file stem. Videos given on the command line replace both.
- `WS/labels.csv`: `video,frame,point,x,y,source` with `source=label` (a click) or `source=hidden` (marked not
  visible; x and y empty).
"""

from __future__ import annotations

import json
from pathlib import Path

from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES
from tracking import labels as labels_csv

CONFIG_NAME = "labeling.json"
LABELS_NAME = "labels.csv"
TRACKS_NAME = "tracks.csv"


def workspace_videos(workspace: Path, given: list[Path] | None = None) -> dict[str, Path]:
    """Video name -> file: the `given` files (named by stem), else `labeling.json`, else `WS/videos/*`."""
    if given:
        return _by_stem(list(given))
    config = workspace / CONFIG_NAME
    if config.is_file():
        try:
            data = json.loads(config.read_text(encoding="utf-8"))
        except OSError as error:
            raise InputError(config, f"cannot read: {error.strerror or error}") from None
        except (ValueError, UnicodeDecodeError, RecursionError) as error:  # ValueError: also >4300-digit ints
            raise InputError(config, f"not valid JSON: {str(error)[:200]}", fix="fix or delete the file") from None
        raw = data.get("videos", {}) if isinstance(data, dict) else None
        if not isinstance(raw, dict) or not all(isinstance(v, str) for v in raw.values()):
            raise InputError(
                config,
                "'videos' must map video names to file paths",
                fix='write {"videos": {"cam01": "videos/cam01.mp4"}}',
            )
        if raw:
            videos = {str(name): workspace / p for name, p in raw.items()}  # an absolute p replaces workspace
            for name, path in videos.items():
                if not path.is_file():
                    raise InputError(
                        config,
                        f"video {name!r}: file {path} not found",
                        fix="fix the path or give the videos with --videos",
                    )
            return videos
    folder = workspace / "videos"
    listed = sorted(folder.iterdir()) if folder.is_dir() else []
    files = [p for p in listed if p.suffix.lower() in VIDEO_SUFFIXES]
    if not files:
        unlabeled = not (workspace / "labels.csv").is_file()  # not a labeling workspace at all: say what comes first
        raise InputError(
            workspace,
            "no videos found (no labeling.json, no videos/ folder" + (", no labels.csv)" if unlabeled else ")"),
            fix="label the subject first (dynrecon label WS --videos V1 V2 ...), or import tracks (dynrecon "
            "import-tracks)"
            if unlabeled
            else "pass --videos V1 V2 ... or put them in WS/videos/",
        )
    return _by_stem(files)


def _by_stem(files: list[Path]) -> dict[str, Path]:
    videos: dict[str, Path] = {}
    for path in files:
        if not path.is_file():
            raise InputError(path, "video file not found", fix="check the path given to --videos")
        if path.stem in videos:
            raise InputError(
                path,
                f"two videos are named {path.stem!r} (also {videos[path.stem]})",
                fix="video names are file stems and must be unique: rename one file",
            )
        videos[path.stem] = path
    return videos


# video -> point -> frame -> (x, y), or None where marked not visible
AllLabels = dict[str, dict[str, dict[int, tuple[float, float] | None]]]


def read_labels(path: Path) -> AllLabels:
    """`labels.csv` -> video -> point -> frame -> (x, y), or None for `source=hidden`. Missing file: no labels.
    The rows come from `tracking.labels`; this only regroups them for tracking."""
    labels: AllLabels = {}
    for (video, frame, point), label in labels_csv.read_labels(path).items():
        labels.setdefault(video, {}).setdefault(point, {})[frame] = (
            None if label.source is labels_csv.Source.HIDDEN else label.xy
        )
    return labels
