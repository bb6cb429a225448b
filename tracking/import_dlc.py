"""DeepLabCut CSV (as written by DLC, or exported from its .h5 with pandas `to_csv`).

Header rows: `scorer`, optionally `individuals` (multi-animal), `bodyparts`, `coords` (`x, y, likelihood`, or
only `x, y` in labeled-data files). The leading index column(s) hold the frame number, or an image path whose
last number is the frame (`labeled-data/cam01/img0012.png`). Empty or NaN cells are missing detections.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from dynrecon.errors import InputError
from dynrecon.readers import csv_records, parse_frame, shown
from tracking.detections import Detection

HEADER_NAMES = ("scorer", "individuals", "bodyparts", "coords")
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")
_NUMBER = re.compile(r"[+-]?[\d.eE+-]+")


def video_name_from_dlc(path: Path) -> str:
    """`cam01DLC_resnet50_projectJan1shuffle1_500000.csv` -> `cam01`; other names -> the file stem."""
    stem = path.stem
    index = stem.find("DLC_")
    return stem[:index] if index > 0 else stem


def read_dlc(path: Path, video: str) -> list[Detection]:
    # Records never span lines (csv_records refuses that), so list index + 1 is the file line.
    rows = [row for _, row in csv_records(path)]
    header: dict[str, list[str]] = {}
    line = 0
    while line < len(rows) and rows[line] and rows[line][0].strip().lower() in HEADER_NAMES:
        header[rows[line][0].strip().lower()] = [c.strip() for c in rows[line]]
        line += 1
    fix = "expected DeepLabCut header rows scorer, [individuals,] bodyparts, coords"
    for name in ("bodyparts", "coords"):
        if name not in header:
            raise InputError(path, f"no '{name}' header row", where=f"line {line + 1}", fix=fix)
    coords = header["coords"]
    parts = header["bodyparts"]
    individuals = header.get("individuals")
    # Leading index columns have no coordinate name (DLC writes 1 to 3 of them).
    first = next((i for i, c in enumerate(coords) if i > 0 and c in ("x", "y", "likelihood")), None)
    if first is None:
        raise InputError(path, "the coords row names no x/y columns", where=f"line {line}", fix=fix)
    columns: dict[str, dict[str, int]] = {}  # point -> coordinate -> column
    for col in range(first, len(coords)):
        coord = coords[col]
        if coord not in ("x", "y", "likelihood"):
            raise InputError(
                path,
                f"column {col + 1} of the coords row is {coord!r}",
                where=f"line {line}",
                fix="coordinates must be x, y or likelihood",
            )
        part = parts[col] if col < len(parts) else ""
        if not part:
            raise InputError(path, f"column {col + 1} has no bodypart name", where="bodyparts row", fix=fix)
        individual = individuals[col] if individuals is not None and col < len(individuals) else ""
        point = f"{individual}_{part}" if individual and individual != "single" else part
        if coord in columns.setdefault(point, {}):
            raise InputError(path, f"two {coord!r} columns for point {point!r}", where=f"column {col + 1}")
        columns[point][coord] = col
    for point, cols in columns.items():
        if "x" not in cols or "y" not in cols:
            raise InputError(path, f"point {point!r} lacks an x or y column", where="coords row", fix=fix)
    detections: list[Detection] = []
    for number, row in enumerate(rows[line:], start=line + 1):
        if not row or all(not c.strip() for c in row):
            continue
        frame = _frame_of(path, number, row[:first])
        for point, cols in columns.items():
            x = _number(path, number, row, cols["x"])
            y = _number(path, number, row, cols["y"])
            likelihood = _number(path, number, row, cols["likelihood"]) if "likelihood" in cols else None
            if x is None or y is None:
                continue
            detections.append(
                Detection(
                    video=video,
                    frame=frame,
                    point=point,
                    x=x,
                    y=y,
                    score=likelihood,
                    where=f"{path.name}:line {number}",
                )
            )
    return detections


def _frame_of(path: Path, number: int, index_cells: list[str]) -> int:
    text = " ".join(c.strip() for c in index_cells if c.strip())
    if _NUMBER.fullmatch(text):  # an index, not an image name: -7 or 2.0 are refused, not read as 7 or 0
        return parse_frame(text, path, f"line {number}")
    match = _LAST_NUMBER.search(text)
    if match is None:
        raise InputError(
            path,
            f"cannot tell the frame number from {shown(text)}",
            where=f"line {number}",
            fix="the first column must be the frame index or an image name ending in a number",
        )
    return parse_frame(match.group(1), path, f"line {number}")


def _number(path: Path, number: int, row: list[str], col: int) -> float | None:
    if col >= len(row):
        raise InputError(path, f"expected at least {col + 1} fields, found {len(row)}", where=f"line {number}")
    cell = row[col].strip()
    if not cell:
        return None
    try:
        value = float(cell)
    except ValueError:
        raise InputError(path, f"{cell!r} in column {col + 1} is not a number", where=f"line {number}") from None
    return value if math.isfinite(value) else None
