"""What `dynrecon track WS` reads from a labeling workspace: the videos and the manual labels.

Layout (shared with `labeling`):
- `WS/labeling.json`: `{"videos": {"cam01": "videos/cam01.mp4", ...}, ...}`, paths relative to WS or absolute;
  without it, `WS/videos/*` named by file stem. Videos given on the command line replace both.
- `WS/labels.csv`: `video,frame,point,x,y,source` with `source=label` (a click) or `source=hidden` (marked not
  visible; x and y empty).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from dynrecon.errors import InputError

CONFIG_NAME = "labeling.json"
LABELS_NAME = "labels.csv"
TRACKS_NAME = "tracks.csv"
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")
HIDDEN_SOURCES = ("hidden",)


def workspace_videos(workspace: Path, given: list[Path] | None = None) -> dict[str, Path]:
    """Video name -> file: the `given` files (named by stem), else `labeling.json`, else `WS/videos/*`."""
    if given:
        return _by_stem(list(given))
    config = workspace / CONFIG_NAME
    if config.is_file():
        try:
            data = json.loads(config.read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as error:
            raise InputError(config, f"not valid JSON: {error}", fix="fix or delete the file") from None
        raw = data.get("videos", {}) if isinstance(data, dict) else None
        if not isinstance(raw, dict) or not all(isinstance(v, str) for v in raw.values()):
            raise InputError(config, "'videos' must map video names to file paths",
                             fix='write {"videos": {"cam01": "videos/cam01.mp4"}}')
        if raw:
            videos = {str(name): workspace / p for name, p in raw.items()}  # an absolute p replaces workspace
            for name, path in videos.items():
                if not path.is_file():
                    raise InputError(config, f"video {name!r}: file {path} not found",
                                     fix="fix the path or give the videos with --videos")
            return videos
    folder = workspace / "videos"
    listed = sorted(folder.iterdir()) if folder.is_dir() else []
    files = [p for p in listed if p.suffix.lower() in VIDEO_SUFFIXES]
    if not files:
        raise InputError(workspace, "no videos found (no labeling.json, no videos/ folder)",
                         fix="pass --videos V1 V2 ... or put them in WS/videos/")
    return _by_stem(files)


def _by_stem(files: list[Path]) -> dict[str, Path]:
    videos: dict[str, Path] = {}
    for path in files:
        if not path.is_file():
            raise InputError(path, "video file not found", fix="check the path given to --videos")
        if path.stem in videos:
            raise InputError(path, f"two videos are named {path.stem!r} (also {videos[path.stem]})",
                             fix="video names are file stems and must be unique: rename one file")
        videos[path.stem] = path
    return videos


# video -> point -> frame -> (x, y), or None where marked not visible
AllLabels = dict[str, dict[str, dict[int, tuple[float, float] | None]]]


def read_labels(path: Path) -> AllLabels:
    """`labels.csv` -> video -> point -> frame -> (x, y), or None for `source=hidden`. Missing file: no
    labels."""
    labels: AllLabels = {}
    try:
        handle = path.open(newline="", encoding="utf-8")
    except FileNotFoundError:
        return labels
    with handle:
        reader = csv.reader(handle)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            return labels
        except (csv.Error, UnicodeDecodeError) as error:
            raise InputError(path, f"not a CSV file: {error}", where="line 1") from None
        missing = [c for c in ("video", "frame", "point", "x", "y") if c not in header]
        if missing:
            raise InputError(path, f"header lacks column(s) {', '.join(missing)}", where="line 1",
                             fix="the header must be video,frame,point,x,y,source")
        col = {name: header.index(name) for name in header}
        try:
            for row in reader:
                if not row or all(not cell.strip() for cell in row):
                    continue
                where = f"line {reader.line_num}"
                if len(row) < len(header):
                    raise InputError(path, f"expected {len(header)} fields, found {len(row)}", where=where)
                video, point = row[col["video"]].strip(), row[col["point"]].strip()
                if not video or not point:
                    raise InputError(path, "empty video or point name", where=where)
                try:
                    frame = int(row[col["frame"]])
                except ValueError:
                    raise InputError(path, f"frame {row[col['frame']]!r} is not an integer",
                                     where=where) from None
                if frame < 0:
                    raise InputError(path, f"frame {frame} is negative", where=where,
                                     fix="frames are 0-based")
                source = row[col["source"]].strip() if "source" in col else "label"
                marks = labels.setdefault(video, {}).setdefault(point, {})
                if frame in marks:
                    raise InputError(path, f"point {point!r} of video {video!r} is labeled twice on frame "
                                     f"{frame}",
                                     where=where, fix="keep one row per video, frame and point")
                if source in HIDDEN_SOURCES:
                    marks[frame] = None
                    continue
                try:
                    x, y = float(row[col["x"]]), float(row[col["y"]])
                except ValueError:
                    raise InputError(path, f"x, y = {row[col['x']]!r}, {row[col['y']]!r} are not numbers",
                                     where=where,
                                     fix="write source=hidden with empty x,y for a hidden point") from None
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise InputError(path, f"x, y = {x}, {y} is not finite", where=where)
                marks[frame] = (x, y)
        except csv.Error as error:
            raise InputError(path, f"malformed CSV: {error}", where=f"line {reader.line_num}") from None
        except UnicodeDecodeError:
            raise InputError(path, "not UTF-8 text", fix="save the file as UTF-8 CSV") from None
    return labels

