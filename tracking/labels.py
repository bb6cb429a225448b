"""`labels.csv`: the user's manual clicks, one row per (video, frame, point) (see docs/formats.md).

Header `video,frame,point,x,y,source`, the `tracks.csv` columns plus `source`:
- `source=label`: the point is at (x, y) in that frame (OpenCV pixels, top-left pixel centre is (0, 0));
- `source=hidden`: the user marked the point "not visible here"; x and y are empty. The tracker must not carry
  the point through that frame from either side.
A missing row means "not labeled". The solver never reads this file; `tracking` turns it into `tracks.csv`.
The format lives here, with its reader `tracking`; the labeling page writes it through `labeling.labels.LabelStore`.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

from dynrecon.atomic import atomic_open
from dynrecon.errors import InputError
from dynrecon.readers import csv_records, header_error, parse_frame, repeated_column, shown

COLUMNS = ("video", "frame", "point", "x", "y", "source")


class Source(Enum):
    LABEL = "label"
    HIDDEN = "hidden"


@dataclass(frozen=True, kw_only=True)
class Label:
    """One manual mark. `xy` is None exactly when `source` is HIDDEN."""

    source: Source
    xy: tuple[float, float] | None = None
    # The labels.csv line it was read from, for error messages; not part of the label's value.
    line: int | None = field(default=None, compare=False)


Key = tuple[str, int, str]  # (video, frame, point)


def read_labels(path: str | Path) -> dict[Key, Label]:
    """Read `labels.csv`; a missing file is an empty set of labels. Errors name the line and the fix."""
    path = Path(path)
    labels: dict[Key, Label] = {}
    if not path.exists() and not path.is_symlink():
        return labels
    records = csv_records(path)
    first = next(records, None)
    if first is None:
        return labels
    header = [h.strip() for h in first[1]]
    missing = [c for c in COLUMNS[:5] if c not in header]
    if missing:
        raise header_error(
            path, header, missing, where=f"line {first[0]}", fix="the header must be video,frame,point,x,y,source"
        )
    repeated_column(path, header, where=f"line {first[0]}")
    col = {name: header.index(name) for name in COLUMNS if name in header}
    first_line: dict[Key, int] = {}
    for number, row in records:
        if not row or all(not cell.strip() for cell in row):
            continue
        where = f"line {number}"
        if len(row) < len(header):
            raise InputError(path, f"expected {len(header)} fields, found {len(row)}", where=where)
        key = _parse_key(path, where, row, col)
        if key in first_line:
            raise InputError(
                path,
                f"point {shown(key[2])} of video {shown(key[0])} is labeled twice on frame "
                f"{key[1]} (first on line {first_line[key]})",
                where=where,
                fix="keep one row per video, frame and point",
            )
        first_line[key] = number
        labels[key] = replace(_parse_label(path, where, row, col), line=number)
    return labels


def _parse_key(path: Path, where: str, row: list[str], col: dict[str, int]) -> Key:
    video, point = row[col["video"]].strip(), row[col["point"]].strip()
    if not video or not point:
        raise InputError(path, "empty video or point name", where=where)
    return video, parse_frame(row[col["frame"]], path, where), point


def _parse_label(path: Path, where: str, row: list[str], col: dict[str, int]) -> Label:
    raw_source = row[col["source"]].strip() if "source" in col else "label"
    try:
        source = Source(raw_source or "label")
    except ValueError:
        raise InputError(path, f"source {shown(raw_source)} is neither 'label' nor 'hidden'", where=where) from None
    if source is Source.HIDDEN:
        return Label(source=source)
    try:
        x, y = float(row[col["x"]]), float(row[col["y"]])
    except ValueError:
        raise InputError(
            path,
            f"x, y = {shown(row[col['x']])}, {shown(row[col['y']])} are not numbers",
            where=where,
            fix="write source=hidden with empty x,y for a point that is not visible",
        ) from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InputError(path, f"x, y = {x}, {y} is not finite", where=where)
    return Label(source=source, xy=(x, y))


def write_labels(path: str | Path, labels: dict[Key, Label], point_order: list[str] | None = None) -> Path:
    """Write `labels.csv` atomically, sorted by video, frame, then point order (given order first)."""
    path = Path(path)
    order = {name: i for i, name in enumerate(point_order or [])}
    keys = sorted(labels, key=lambda k: (k[0], k[1], order.get(k[2], len(order)), k[2]))
    with atomic_open(path, "w", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(COLUMNS)
        for key in keys:
            label = labels[key]
            x, y = ("", "") if label.xy is None else (f"{label.xy[0]:.3f}", f"{label.xy[1]:.3f}")
            writer.writerow([key[0], key[1], key[2], x, y, label.source.value])
    return path
