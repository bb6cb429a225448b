"""`tracks.csv`: observed 2D points, one row per (video, frame, point) (see docs/formats.md).

Header `video,frame,point,x,y`; extra columns (e.g. `source`, `score`) are kept as strings and ignored by the
solver. A missing row means "not observed". Pixel coordinates follow OpenCV (top-left pixel centre is (0, 0)).
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dynrecon.atomic import atomic_open
from dynrecon.errors import InputError
from dynrecon.names import spelled_alike
from dynrecon.readers import MAX_FRAME, csv_records, header_error, parse_frame, repeated_column, shown

log = logging.getLogger(__name__)

REQUIRED_COLUMNS = ("video", "frame", "point", "x", "y")
# Values of the optional `source` column written by dynrecon (importers write their own, e.g. "charuco").
SOURCE_LABEL = "label"  # a manual label, copied from labels.csv
SOURCE_TRACK = "track"  # carried there by the tracker
# Observations and labels may lie this share of the image size outside it (a point just off the edge, or on an
# undistorted image); further out they are false detections or typos.
IMAGE_MARGIN = 0.1


def inside_image(xy: np.ndarray, width: float | np.ndarray, height: float | np.ndarray) -> np.ndarray:
    """(N,) bool: which (N, 2) pixel positions are finite and inside the image (sizes scalar or (N,)) with
    IMAGE_MARGIN of its size around it."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    size = np.stack(np.broadcast_arrays(np.asarray(width, dtype=float), np.asarray(height, dtype=float)), axis=-1)
    # OpenCV pixels: the image covers [-0.5, width - 0.5] x [-0.5, height - 0.5].
    low = -0.5 - IMAGE_MARGIN * size
    high = size - 0.5 + IMAGE_MARGIN * size
    with np.errstate(invalid="ignore"):
        return np.all(np.isfinite(xy) & (xy >= low) & (xy <= high), axis=1)


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

    def take(self, index: np.ndarray | list[int]) -> Tracks:
        """The rows `index` (in that order), with their extra columns and source lines."""
        index = np.asarray(index, dtype=np.int64)
        return Tracks(
            video=[self.video[i] for i in index],
            frame=self.frame[index],
            point=[self.point[i] for i in index],
            xy=self.xy[index],
            extra={k: [v[i] for i in index] for k, v in self.extra.items()},
            line=None if self.line is None else self.line[index],
            path=self.path,
        )

    def canonical(self) -> Tracks:
        """The same rows sorted by (video, frame, point): what is computed from them does not depend on the
        order the rows came in."""
        if not len(self):
            return self
        order = np.lexsort((_ranks(self.point), self.frame, _ranks(self.video)))
        return self.take(order)

    def of_videos(self, names: Iterable[str]) -> Tracks:
        """The rows of the videos `names`, in their order here."""
        wanted = set(names)
        return self.take([i for i, video in enumerate(self.video) if video in wanted])

    @classmethod
    def from_rows(cls, rows: list[tuple[str, int, str, float, float]], **extra: list[str]) -> Tracks:
        return cls(
            video=[r[0] for r in rows],
            frame=np.array([r[1] for r in rows], dtype=np.int64),
            point=[r[2] for r in rows],
            xy=np.array([(r[3], r[4]) for r in rows], dtype=float).reshape(-1, 2),
            extra={k: list(v) for k, v in extra.items()},
        )


def matched_to_videos(tracks: Tracks, videos: Iterable[str]) -> Tracks:
    """`tracks` with each video name that names none of `videos` renamed to the one video whose name it matches
    when case, separators, leading zeros and a file suffix are ignored (`back.mp4` -> `back`, `Cam01` -> `cam_1`),
    with a warning. Names that match no video, or several, or a video the tracks already name, stay as they are."""
    videos = list(videos)
    named = set(tracks.video_names())
    alike = {name: spelled_alike(name, videos) for name in named - set(videos)}
    renamed = {name: found[0] for name, found in alike.items() if len(found) == 1 and found[0] not in named}
    targets = list(renamed.values())
    renamed = {old: new for old, new in renamed.items() if targets.count(new) == 1}
    for name in sorted(set(alike) - set(renamed)):
        if alike[name]:  # spelled like a video, but another name already takes it (or several videos match)
            log.warning(
                "%s: video %r names none of the videos, and is not taken as %s (another name of the tracks is, or "
                "several videos match)",
                tracks.path or "tracks",
                name,
                " or ".join(repr(v) for v in alike[name]),
            )
    if not renamed:
        return tracks
    for old, new in sorted(renamed.items()):
        log.warning("%s: video %r taken as the video %r", tracks.path or "tracks", old, new)
    return dataclasses.replace(tracks, video=[renamed.get(v, v) for v in tracks.video])


def join_tracks(*parts: Tracks) -> Tracks:
    """The rows of every part, in order (video, frame, point, xy; extra columns dropped)."""
    return Tracks(
        video=[v for t in parts for v in t.video],
        frame=np.concatenate([t.frame for t in parts]).astype(np.int64) if parts else np.zeros(0, np.int64),
        point=[p for t in parts for p in t.point],
        xy=np.concatenate([t.xy for t in parts]).reshape(-1, 2) if parts else np.zeros((0, 2)),
    )


def read_tracks(path: str | Path) -> Tracks:
    """Read and validate `tracks.csv`. Errors name the line; duplicates name both lines."""
    path = Path(path)
    fast = _read_regular(path)
    return fast if fast is not None else _read_checked(path)


def _read_regular(path: Path) -> Tracks | None:
    """`tracks.csv` read column-wise when it is plain: no quote, CR or NUL, one record per line, no blank line, every
    line with the header's number of cells, and every value valid; then csv's cells are the text split at commas
    and line ends. None otherwise (or on any error): `_read_checked` then reads it row by row and names the line at
    fault. Both give the same `Tracks`: cells are converted by the same int() and float()."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            text = handle.read()
    except (OSError, UnicodeDecodeError):
        return None
    if not text or '"' in text or "\r" in text or "\0" in text:
        return None
    lines = text.split("\n")
    if lines[-1] == "":
        lines.pop()
    if max(map(len, lines)) > csv.field_size_limit():  # csv refuses such a cell: the checked reader says where
        return None
    header = [h.strip() for h in lines[0].split(",")]
    width = len(header)
    if (
        any(c not in header for c in REQUIRED_COLUMNS)
        or len(set(header)) < width  # a repeated column (or two empty names): the checked reader says which
        or set(map(str.count, lines, itertools.repeat(","))) != {width - 1}
    ):
        return None
    cells = "\n".join(lines).replace("\n", ",").split(",")  # flat: strings, no per-row lists
    columns = [cells[width + k :: width] for k in range(width)]
    count = len(lines) - 1
    index = {name: header.index(name) for name in REQUIRED_COLUMNS}
    videos = list(map(str.strip, columns[index["video"]]))
    points = list(map(str.strip, columns[index["point"]]))
    if not all(videos) or not all(points):
        return None
    if any("_" in text for text in columns[index["frame"]]):
        return None  # int() reads 1_000 as 1000: the checked reader says which line
    try:
        frame_numbers = list(map(int, columns[index["frame"]]))
        frames = np.array(frame_numbers, dtype=np.int64)
        xy = np.column_stack(
            [np.array(list(map(float, columns[index[c]])), dtype=float).reshape(-1) for c in ("x", "y")]
        ).reshape(-1, 2)
    except (ValueError, OverflowError):
        return None
    if len(frames) and (frames.min() < 0 or frames.max() >= MAX_FRAME):
        return None
    if not np.isfinite(xy).all() or _repeats(videos, frames, points):
        return None
    extra_names = [h for h in header if h not in REQUIRED_COLUMNS and h]
    return Tracks(
        video=videos,
        frame=frames,
        point=points,
        xy=xy,
        extra={name: list(columns[header.index(name)]) for name in extra_names},
        line=np.arange(2, count + 2, dtype=np.int64),
        path=path,
    )


def _repeats(videos: list[str], frames: np.ndarray, points: list[str]) -> bool:
    """Whether a (video, frame, point) appears twice; on integer codes (a set of N tuples is slow to collect)."""
    if len(frames) < 2:
        return False
    codes = [_codes(videos), frames, _codes(points)]
    order = np.lexsort(codes)
    same = np.ones(len(frames) - 1, dtype=bool)
    for code in codes:
        ordered = code[order]
        same &= ordered[1:] == ordered[:-1]
    return bool(same.any())


def _codes(names: list[str]) -> np.ndarray:
    """(N,) int64: each name's index among the distinct names."""
    index = {name: i for i, name in enumerate(dict.fromkeys(names))}
    return np.fromiter(map(index.__getitem__, names), dtype=np.int64, count=len(names))


def _ranks(names: list[str]) -> np.ndarray:
    """(N,) int64: each name's rank among the distinct names, sorted."""
    return np.unique(np.asarray(names, dtype=str), return_inverse=True)[1].astype(np.int64)


def _read_checked(path: Path) -> Tracks:
    """`tracks.csv` read and validated row by row: errors name the line."""
    videos: list[str] = []
    frames: list[int] = []
    points: list[str] = []
    xy: list[tuple[float, float]] = []
    lines: list[int] = []
    records = csv_records(path, missing_fix="run `dynrecon track` or give the right path")
    first = next(records, None)
    if first is None:
        raise InputError(
            path, "file is empty", where="line 1", fix="the first line must be the header video,frame,point,x,y"
        )
    header = [h.strip() for h in first[1]]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise header_error(
            path, header, missing, where=f"line {first[0]}", fix="the header must contain video,frame,point,x,y"
        )
    repeated_column(path, header, where=f"line {first[0]}")
    index = {name: header.index(name) for name in REQUIRED_COLUMNS}
    extra_names = [h for h in header if h not in REQUIRED_COLUMNS and h]
    extra_index = {name: header.index(name) for name in extra_names}
    extras: dict[str, list[str]] = {name: [] for name in extra_names}
    seen: dict[tuple[str, int, str], int] = {}
    for number, row in records:
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) < len(header) or any(cell.strip() for cell in row[len(header) :]):
            # a cell beyond the header belongs to no column: a comma too many moved the others
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
                path,
                f"x, y = {shown(row[index['x']])}, {shown(row[index['y']])} are not numbers",
                where=f"line {number}",
                fix="a point not seen in a frame has no row: leave the row out",
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
                f"duplicate observation of point {shown(point)} in video {shown(video)} frame "
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
