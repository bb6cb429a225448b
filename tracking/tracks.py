"""`tracks.csv`: observed 2D points, one row per (video, frame, point) (see docs/formats.md).

Header `video,frame,point,x,y`; extra columns (e.g. `source`, `score`) are kept as strings and ignored by the
solver. A missing row means "not observed". Pixel coordinates follow OpenCV (top-left pixel centre is (0, 0)).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dynrecon.atomic import atomic_open
from dynrecon.errors import InputError
from dynrecon.readers import parse_frame

REQUIRED_COLUMNS = ("video", "frame", "point", "x", "y")
# Values of the optional `source` column written by dynrecon (importers write their own, e.g. "charuco").
SOURCE_LABEL = "label"  # a manual label, copied from labels.csv
SOURCE_TRACK = "track"  # carried there by the tracker


@dataclass(kw_only=True)
class Tracks:
    """Columns of `tracks.csv`; row i is one observation. `line` is the 1-based line in the file it came from."""

    video: list[str] = field(default_factory=list)
    frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (N,)
    point: list[str] = field(default_factory=list)
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (N, 2) pixels
    extra: dict[str, list[str]] = field(default_factory=dict)  # column name -> N strings
    line: np.ndarray | None = None  # (N,) source line numbers, None when built in memory
    path: Path | None = None

    def __len__(self) -> int:
        return len(self.video)

    def point_names(self) -> list[str]:
        """Point names in order of first appearance."""
        return list(dict.fromkeys(self.point))

    def video_names(self) -> list[str]:
        return list(dict.fromkeys(self.video))

    def where(self, row: int) -> str:
        return f"line {int(self.line[row])}" if self.line is not None else f"row {row}"

    @classmethod
    def from_rows(cls, rows: list[tuple[str, int, str, float, float]], **extra: list[str]) -> Tracks:
        return cls(
            video=[r[0] for r in rows],
            frame=np.array([r[1] for r in rows], dtype=np.int64),
            point=[r[2] for r in rows],
            xy=np.array([(r[3], r[4]) for r in rows], dtype=float).reshape(-1, 2),
            extra={k: list(v) for k, v in extra.items()},
        )


def read_tracks(path: str | Path) -> Tracks:
    """Read and validate `tracks.csv`. Errors name the line; duplicates name both lines."""
    path = Path(path)
    try:
        handle = path.open(newline="", encoding="utf-8")
    except FileNotFoundError:
        raise InputError(path, "file not found", fix="run `dynrecon track` or give the right path") from None
    except OSError as error:  # a folder, or no permission
        raise InputError(path, f"cannot read: {error.strerror or error}", fix="give the path of a CSV file") from None
    videos: list[str] = []
    frames: list[int] = []
    points: list[str] = []
    xy: list[tuple[float, float]] = []
    lines: list[int] = []
    with handle:
        reader = csv.reader(handle)
        try:
            header = next(reader)
        except StopIteration:
            raise InputError(
                path, "file is empty", where="line 1", fix="the first line must be the header video,frame,point,x,y"
            ) from None
        except (csv.Error, UnicodeDecodeError) as error:
            raise InputError(path, f"not a CSV file: {error}", where="line 1") from None
        header = [h.strip() for h in header]
        missing = [c for c in REQUIRED_COLUMNS if c not in header]
        if missing:
            raise InputError(
                path,
                f"header lacks column(s) {', '.join(missing)}",
                where="line 1",
                fix="the header must contain video,frame,point,x,y",
            )
        index = {name: header.index(name) for name in REQUIRED_COLUMNS}
        extra_names = [h for h in header if h not in REQUIRED_COLUMNS and h]
        extra_index = {name: header.index(name) for name in extra_names}
        extras: dict[str, list[str]] = {name: [] for name in extra_names}
        seen: dict[tuple[str, int, str], int] = {}
        try:
            for row in reader:
                number = reader.line_num
                if not row or all(not cell.strip() for cell in row):
                    continue
                if len(row) < len(header):
                    raise InputError(path, f"expected {len(header)} fields, found {len(row)}", where=f"line {number}")
                video = row[index["video"]].strip()
                point = row[index["point"]].strip()
                if not video or not point:
                    raise InputError(path, "empty video or point name", where=f"line {number}")
                frame = parse_frame(row[index["frame"]], path, f"line {number}")
                try:
                    x, y = float(row[index["x"]]), float(row[index["y"]])
                except ValueError:
                    raise InputError(
                        path, f"x, y = {row[index['x']]!r}, {row[index['y']]!r} are not numbers", where=f"line {number}"
                    ) from None
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise InputError(
                        path,
                        f"x, y = {x}, {y} is not finite",
                        where=f"line {number}",
                        fix="leave unobserved points out instead of writing NaN",
                    )
                key = (video, frame, point)
                if key in seen:
                    raise InputError(
                        path,
                        f"duplicate observation of point {point!r} in video {video!r} frame "
                        f"{frame} (first on line {seen[key]})",
                        where=f"line {number}",
                        fix="keep one row per video, frame and point",
                    )
                seen[key] = number
                videos.append(video)
                frames.append(frame)
                points.append(point)
                xy.append((x, y))
                lines.append(number)
                for name, column in extra_index.items():
                    extras[name].append(row[column] if column < len(row) else "")
        except csv.Error as error:
            raise InputError(path, f"malformed CSV: {error}", where=f"line {reader.line_num}") from None
        except UnicodeDecodeError:
            raise InputError(path, "not UTF-8 text", fix="save the file as UTF-8 CSV") from None
    return Tracks(
        video=videos,
        frame=np.array(frames, dtype=np.int64),
        point=points,
        xy=np.array(xy, dtype=float).reshape(-1, 2),
        extra=extras,
        line=np.array(lines, dtype=np.int64),
        path=path,
    )


def write_tracks(path: str | Path, tracks: Tracks) -> Path:
    """Write `tracks.csv` atomically, sorted by video, frame, point order of first appearance."""
    path = Path(path)
    point_order = {name: i for i, name in enumerate(tracks.point_names())}
    order = sorted(
        range(len(tracks)), key=lambda i: (tracks.video[i], int(tracks.frame[i]), point_order[tracks.point[i]])
    )
    extra_names = list(tracks.extra)
    with atomic_open(path, "w", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow([*REQUIRED_COLUMNS, *extra_names])
        for i in order:
            writer.writerow(
                [
                    tracks.video[i],
                    int(tracks.frame[i]),
                    tracks.point[i],
                    repr(float(tracks.xy[i, 0])),
                    repr(float(tracks.xy[i, 1])),
                    *(tracks.extra[name][i] for name in extra_names),
                ]
            )
    return path
