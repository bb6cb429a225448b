"""`points3d.csv` (also the layout of a simulation's `truth.csv`) and `sequencing.json` (see docs/formats.md).

`points3d.csv` has one row for every posed (video, frame) and every point name, including unobserved points
(`observed` = 0). A point that could not be reconstructed has empty x, y, z. Extra numeric columns (e.g. `time`,
trust measures) may follow the required ones.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.atomic import atomic_open, atomic_write_text
from dynrecon.errors import InputError
from dynrecon.readers import check_frame, csv_records, parse_frame, read_json, repeated_column, shown

POINT_COLUMNS = ("video", "frame", "point", "x", "y", "z", "observed")
# points3d.csv `views` below this: the row's depth no second video measured (reconstruct/views.py), flagged in the
# file and left out of the exports
SINGLE_VIEW = 2


@dataclass(kw_only=True)
class FramePoints:
    """3D points of every frame. Frame i is (videos[i], frames[i])."""

    videos: list[str]
    frames: np.ndarray  # (F,) int frame numbers
    point_names: list[str]  # (P,)
    xyz: np.ndarray  # (F, P, 3), NaN where not reconstructed
    observed: np.ndarray  # (F, P) bool
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (F, P) floats (NaN = empty)

    @property
    def num_frames(self) -> int:
        return len(self.videos)

    def index(self) -> dict[tuple[str, int], int]:
        return {(v, int(f)): i for i, (v, f) in enumerate(zip(self.videos, self.frames, strict=True))}


def _format(value: float) -> str:
    return "" if not math.isfinite(value) else repr(float(value))


def write_points(path: str | Path, points: FramePoints) -> Path:
    path = Path(path)
    extra_names = list(points.extra)
    # Whole columns formatted at once (frame-major, then point, as the rows run) and joined into lines: the text
    # csv.writer writes (names quoted by it, numbers never need quotes), at list speed.
    prefixes = [
        f"{_cell(video)},{frame},"
        for video, frame in zip(points.videos, np.asarray(points.frames, dtype=np.int64).tolist(), strict=True)
    ]
    names = [_cell(name) for name in points.point_names]
    columns = [
        [prefix + name for prefix in prefixes for name in names],
        *(_column(points.xyz[..., axis]) for axis in range(3)),
        np.where(points.observed.astype(bool).ravel(), "1", "0").tolist(),
        *(_column(points.extra[e], integer=e in COUNT_COLUMNS) for e in extra_names),
    ]
    lines = map(",".join, zip(*columns, strict=True))
    with atomic_open(path, "w", newline="") as handle:
        csv.writer(handle, lineterminator="\n").writerow([*POINT_COLUMNS, *extra_names])
        while chunk := list(itertools.islice(lines, _ROWS_PER_WRITE)):
            handle.write("\n".join(chunk) + "\n")
    return path


_ROWS_PER_WRITE = 1 << 16
# Below this share of distinct values among a column's sampled values, each distinct value is formatted once.
_REPEATED_SHARE = 0.5


def _cell(text: str) -> str:
    """`text` as csv.writer writes it inside a row of several cells (quoted where it must be)."""
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\n").writerow([text, ""])
    return buffer.getvalue()[:-2]


# Extra columns that hold counts or 0/1 (docs/formats.md): written as integers, so that `flag == 1` matches as text.
COUNT_COLUMNS = frozenset({"flag", "views", "component"})


def _column(values: np.ndarray, integer: bool = False) -> list[str]:
    """`_format` of every value of an (F, P) array, frame-major; `integer`: whole values without ".0"."""
    flat = np.ascontiguousarray(values, dtype=float).ravel()
    bits = flat.view(np.int64)  # distinct bit patterns: -0.0 and 0.0 are written differently
    if len(bits) > 4096 and any(
        len(np.unique(sample)) < _REPEATED_SHARE * len(sample)
        for sample in (bits[:1024], bits[:: len(bits) // 1024])  # a frame's run of points, and across frames
    ):
        distinct, inverse = np.unique(bits, return_inverse=True)
        texts = _texts(distinct.view(float), integer)
        return list(map(texts.__getitem__, inverse.ravel().tolist()))
    return _texts(flat, integer)


def _texts(values: np.ndarray, integer: bool = False) -> list[str]:
    """repr of each (N,) value, "" where not finite; `integer`: whole values as integers."""
    texts = list(map(float.__repr__, values.tolist()))
    if integer:
        for i in np.flatnonzero(np.isfinite(values) & (values == np.round(values))).tolist():
            texts[i] = str(int(values[i]))
    for i in np.flatnonzero(~np.isfinite(values)).tolist():
        texts[i] = ""
    return texts


MAX_COORDINATE = 1e12  # |x|, |y|, |z| in the file's units: beyond it a corrupt value, not a position


def _number(text: str, column: str, path: Path, where: str) -> float:
    """A cell as a float; empty is NaN."""
    if text.strip() == "":
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise InputError(path, f"{column} {text.strip()[:40]!r} is not a number", where=where) from None


def read_points(path: str | Path) -> FramePoints:
    """Read `points3d.csv` or `truth.csv` back into arrays."""
    path = Path(path)
    frame_index: dict[tuple[str, int], int] = {}
    point_index: dict[str, int] = {}
    records: list[tuple[int, int, list[float], bool, list[float]]] = []
    lines: dict[tuple[int, int], int] = {}
    rows = csv_records(path)
    first = next(rows, None)
    header = None if first is None else [cell.strip() for cell in first[1]]
    if header is None or any(c not in header for c in POINT_COLUMNS):
        raise InputError(path, "header must start with " + ",".join(POINT_COLUMNS), where="line 1")
    repeated_column(path, header, where="line 1")
    col = {name: header.index(name) for name in header}
    extra_names = [h for h in header if h not in POINT_COLUMNS]
    for number, row in rows:
        if not row:
            continue
        where = f"line {number}"
        if len(row) < len(header):
            raise InputError(path, f"expected {len(header)} fields, found {len(row)}", where=where)
        key = (row[col["video"]], parse_frame(row[col["frame"]], path, where))
        values = [_number(row[col[c]], c, path, where) for c in ("x", "y", "z")]
        if len({math.isnan(v) for v in values}) > 1:
            raise InputError(path, "x, y, z are partly empty", where=where, fix="give all three, or none where unknown")
        flag = row[col["observed"]].strip()
        if flag not in ("0", "1", ""):
            raise InputError(path, f"observed is {flag!r}", where=where, fix="observed is 1 (seen) or 0")
        observed = flag == "1"
        extras = [_number(row[col[e]], e, path, where) for e in extra_names]
        if not all(abs(v) < MAX_COORDINATE for v in values if not math.isnan(v)):
            raise InputError(
                path,
                f"x, y, z {values} are not finite or implausible",
                where=where,
                fix=f"coordinates are below {MAX_COORDINATE:g} in magnitude; leave them empty where unknown",
            )
        fi = frame_index.setdefault(key, len(frame_index))
        pi = point_index.setdefault(row[col["point"]], len(point_index))
        if (fi, pi) in lines:  # which of two positions is meant cannot be told
            raise InputError(
                path,
                f"point {row[col['point']]!r} of frame {key[1]} of video {key[0]!r} is also on line {lines[fi, pi]}",
                where=where,
                fix="keep one row per video, frame and point",
            )
        lines[fi, pi] = number
        records.append((fi, pi, values, observed, extras))
    F, P = len(frame_index), len(point_index)
    xyz = np.full((F, P, 3), np.nan)
    observed_arr = np.zeros((F, P), dtype=bool)
    extra = {name: np.full((F, P), np.nan) for name in extra_names}
    for fi, pi, values, observed, extras in records:
        xyz[fi, pi] = values
        observed_arr[fi, pi] = observed
        for name, value in zip(extra_names, extras, strict=True):
            extra[name][fi, pi] = value
    keys = list(frame_index)
    return FramePoints(
        videos=[k[0] for k in keys],
        frames=np.array([k[1] for k in keys], dtype=np.int64),
        point_names=list(point_index),
        xyz=xyz,
        observed=observed_arr,
        extra=extra,
    )


# ---------------------------------------------------------------------------------------------------------------
# sequencing.json


@dataclass(kw_only=True)
class Sequencing:
    """Non-zero coefficients of W: frame i is expressed as sum_k weight[i][k] * shape(neighbours[i][k])."""

    videos: list[str]
    frames: np.ndarray  # (F,)
    neighbours: list[np.ndarray]  # F arrays of frame indices into (videos, frames)
    weights: list[np.ndarray]  # F arrays of coefficients, each summing to 1
    extra: dict[str, Any] = field(default_factory=dict)  # further top-level keys (e.g. clocks)


def write_sequencing(path: str | Path, sequencing: Sequencing) -> Path:
    atomic_write_text(path, _sequencing_text(sequencing))
    return Path(path)


def _sequencing_text(sequencing: Sequencing) -> str:
    """The text of `json.dumps({"frames": [...], **extra}, indent=1) + newline`, built from pieces: json's indented
    encoder runs in Python, one call per value."""
    extra = sequencing.extra
    if "frames" in extra or not all(isinstance(key, str) for key in extra):
        return json.dumps(_sequencing_document(sequencing), indent=1) + "\n"
    names = {name: json.dumps(name) for name in dict.fromkeys(sequencing.videos)}
    frames = [int(f) for f in sequencing.frames]
    video = [names[name] for name in sequencing.videos]
    # a neighbour's entry up to its weight, per frame it names
    reference = [
        f'    {{\n     "video": {v},\n     "frame": {f},\n     "weight": ' for v, f in zip(video, frames, strict=False)
    ]
    entries = []
    for i in range(len(video)):
        neighbours = [
            reference[j] + _json_float(w) + "\n    }"
            for j, w in zip(
                np.asarray(sequencing.neighbours[i], dtype=np.int64).tolist(),
                np.asarray(sequencing.weights[i]).tolist(),
                strict=True,
            )
        ]
        listed = "[\n" + ",\n".join(neighbours) + "\n   ]" if neighbours else "[]"
        entries.append(f'  {{\n   "video": {video[i]},\n   "frame": {frames[i]},\n   "neighbours": {listed}\n  }}')
    parts = ['"frames": ' + ("[\n" + ",\n".join(entries) + "\n ]" if entries else "[]")]
    parts += [json.dumps(key) + ": " + json.dumps(value, indent=1).replace("\n", "\n ") for key, value in extra.items()]
    return "{\n " + ",\n ".join(parts) + "\n}\n"


def _json_float(value: float) -> str:
    """A float as json.dumps writes it (int() first where given an integer, as float(w) did)."""
    value = float(value)
    return float.__repr__(value) if math.isfinite(value) else json.dumps(value)


def _sequencing_document(sequencing: Sequencing) -> dict[str, Any]:
    frames = []
    for i in range(len(sequencing.videos)):
        frames.append(
            {
                "video": sequencing.videos[i],
                "frame": int(sequencing.frames[i]),
                "neighbours": [
                    {"video": sequencing.videos[int(j)], "frame": int(sequencing.frames[int(j)]), "weight": float(w)}
                    for j, w in zip(sequencing.neighbours[i], sequencing.weights[i], strict=True)
                ],
            }
        )
    return {"frames": frames, **sequencing.extra}


def _short(error: Exception) -> str:
    # A KeyError of a huge or deeply nested key would repeat it whole in the one-line message.
    text = repr(error) if isinstance(error, KeyError) else str(error)
    return text if len(text) <= 200 else f"{text[:200]}..."


def read_sequencing(path: str | Path) -> Sequencing:
    path = Path(path)
    document = read_json(path)
    try:
        entries = document["frames"]
        videos = [e["video"] for e in entries]
        frames = np.array(
            [check_frame(e["frame"], path, f"frames[{i}]") for i, e in enumerate(entries)], dtype=np.int64
        )
        index = {(v, int(f)): i for i, (v, f) in enumerate(zip(videos, frames, strict=True))}
        neighbours = [
            np.array([index[(n["video"], n["frame"])] for n in e["neighbours"]], dtype=np.int64) for e in entries
        ]
        weights = [np.array([float(n["weight"]) for n in e["neighbours"]]) for e in entries]
    except (ValueError, KeyError, TypeError, OverflowError) as error:
        raise InputError(path, f"not a valid sequencing.json: {_short(error)}") from None
    for i, w in enumerate(weights):
        bad = np.flatnonzero(~(np.isfinite(w) & (w >= 0)))
        if bad.size:
            raise InputError(
                path,
                f"weight {float(w[bad[0]])} of neighbour {int(bad[0])} is not a finite number >= 0",
                where=f"video {shown(videos[i])} frame {int(frames[i])}",
                fix="weights are >= 0 and sum to 1 per frame; write sequencing.json again with dynrecon solve",
            )
    extra = {k: v for k, v in document.items() if k != "frames"}
    return Sequencing(videos=videos, frames=frames, neighbours=neighbours, weights=weights, extra=extra)
