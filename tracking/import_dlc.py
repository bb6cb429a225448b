"""DeepLabCut output: its CSV (as written by DLC, or exported with pandas `to_csv`) and its .h5 (DLC's default
output: a pandas table under the key `df_with_missing`, or `tracks` for stitched multi-animal tracklets).

Header (CSV rows, or the .h5 columns' levels): `scorer`, optionally `individuals` (multi-animal), `bodyparts`,
`coords` (`x, y, likelihood`, or only `x, y` in labeled-data files). The index holds the frame number, or an image
path whose last number is the frame (`labeled-data/cam01/img0012.png`). Empty or NaN cells are missing detections.

Multi-animal files name each point `<individual>_<bodypart>` (the `single` individual's unique bodyparts keep their
bare names). DLC's identities hold within a video, not across separately analysed videos (unless the model was
trained to tell the animals apart): `person` / `every_person` number the individuals by how much they are seen, as
OpenPose's people are (`tracking.people.person_point`), so that `register` can match them across the videos.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from dynrecon.readers import csv_records, parse_frame, separator_hint, shown
from tracking.detections import Detection
from tracking.people import individual_names, tool_name

HEADER_NAMES = ("scorer", "individuals", "bodyparts", "coords")
H5_SUFFIXES = (".h5", ".hdf5")
H5_KEYS = ("df_with_missing", "tracks")  # DLC's keys: video analysis, stitched multi-animal tracklets
SINGLE = "single"  # DLC's individual for the unique bodyparts of a multi-animal project
_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")
_NUMBER = re.compile(r"[+-]?[\d.eE+-]+")
_FIX = "expected DeepLabCut header rows scorer, [individuals,] bodyparts, coords"


@dataclass(kw_only=True)
class _Table:
    """A DLC file read: per point (individual, bodypart) its coordinate columns of `values`."""

    columns: dict[tuple[str, str], dict[str, int]]  # (individual or "", bodypart) -> coordinate -> column
    frames: np.ndarray  # (R,) frame of each row
    values: np.ndarray  # (R, C) floats, NaN = empty
    where: list[str]  # (R,) "line N" / "row N", for messages


def video_name_from_dlc(path: Path) -> str:
    """`cam01DLC_resnet50_projectJan1shuffle1_500000.csv` -> `cam01` (DeepLabCut 2.0's `cam01DeepCut_resnet50_...`
    too); a labelled-data file, `labeled-data/cam01/CollectedData_<scorer>.csv` -> its folder's name, `cam01`;
    other names -> the file stem."""
    stem = path.stem
    if stem.startswith("CollectedData_") and path.parent.parent.name == "labeled-data":  # DeepLabCut's project layout
        return path.parent.name
    found = [i for i in (stem.find("DLC_"), stem.find("DeepCut_")) if i > 0]
    return stem[: min(found)] if found else stem


def read_dlc(path: Path, video: str, person: int | None = None, every_person: bool = False) -> list[Detection]:
    """The detections of a DLC CSV or .h5 file. Multi-animal: `person` N keeps the individual seen N-th most (bare
    bodypart names), `every_person` names every individual's points person<N>_<bodypart>; neither keeps DLC's
    names, `<individual>_<bodypart>`."""
    table = _read_h5(path) if path.suffix.lower() in H5_SUFFIXES else _read_csv(path)
    counts = {key: int(np.isfinite(table.values[:, cols["x"]]).sum()) for key, cols in table.columns.items()}
    names = individual_names(path, counts, person, every_person)
    detections: list[Detection] = []
    for key, cols in table.columns.items():
        name = names.get(key)
        if name is None:
            continue
        x, y = table.values[:, cols["x"]], table.values[:, cols["y"]]
        likelihood = table.values[:, cols["likelihood"]] if "likelihood" in cols else None
        for r in np.flatnonzero(np.isfinite(x) & np.isfinite(y)):
            score = None if likelihood is None or math.isnan(likelihood[r]) else float(likelihood[r])
            detections.append(
                Detection(
                    video=video,
                    frame=int(table.frames[r]),
                    point=name,
                    x=float(x[r]),
                    y=float(y[r]),
                    score=score,
                    where=f"{path.name}:{table.where[r]}",
                )
            )
    return detections


def _columns(path: Path, header: dict[str, list[str]], first: int, where: str) -> dict[tuple[str, str], dict[str, int]]:
    """(individual, bodypart) -> coordinate -> column, from the header's rows, which include bodyparts and coords
    (`first`: the first data column)."""
    coords, parts, individuals = header["coords"], header["bodyparts"], header.get("individuals")
    columns: dict[tuple[str, str], dict[str, int]] = {}
    for col in range(first, len(coords)):
        coord = coords[col]
        if coord not in ("x", "y", "likelihood"):
            raise InputError(
                path,
                f"column {col + 1} of the coords row is {coord!r}",
                where=where,
                fix="coordinates must be x, y or likelihood",
            )
        part = parts[col] if col < len(parts) else ""
        if not part:
            raise InputError(path, f"column {col + 1} has no bodypart name", where="bodyparts row", fix=_FIX)
        individual = individuals[col] if individuals is not None and col < len(individuals) else ""
        key = ("" if individual == SINGLE else individual, part)
        if coord in columns.setdefault(key, {}):
            raise InputError(path, f"two {coord!r} columns for point {tool_name(*key)!r}", where=f"column {col + 1}")
        columns[key][coord] = col
    for key, cols in columns.items():
        if "x" not in cols or "y" not in cols:
            raise InputError(path, f"point {tool_name(*key)!r} lacks an x or y column", where="coords row", fix=_FIX)
    return columns


def _read_csv(path: Path) -> _Table:
    # Records never span lines (csv_records refuses that), so list index + 1 is the file line.
    rows = [row for _, row in csv_records(path)]
    header: dict[str, list[str]] = {}
    line = 0
    while line < len(rows) and rows[line] and rows[line][0].strip().lower() in HEADER_NAMES:
        header[rows[line][0].strip().lower()] = [c.strip() for c in rows[line]]
        line += 1
    coords = header.get("coords", [])
    # Leading index columns have no coordinate name (DLC writes 1 to 3 of them).
    first = next((i for i, c in enumerate(coords) if i > 0 and c in ("x", "y", "likelihood")), None)
    if not rows:
        raise InputError(path, "the file is empty", fix="export the detections again (DeepLabCut's analyze_videos)")
    for name in ("bodyparts", "coords"):
        if name not in header:
            # another separator leaves each header row one cell: say so rather than name a row
            said = separator_hint(rows[0])
            raise InputError(path, f"no '{name}' header row{said}", where=f"line {line + 1}", fix=_FIX)
    if first is None:
        raise InputError(path, "the coords row names no x/y columns", where=f"line {line}", fix=_FIX)
    columns = _columns(path, header, first, f"line {line}")
    width = max(c for cols in columns.values() for c in cols.values()) + 1
    frames, values, where = [], [], []
    for number, row in enumerate(rows[line:], start=line + 1):
        if not row or all(not c.strip() for c in row):
            continue
        frames.append(_frame_of(path, f"line {number}", row[:first]))
        values.append([_number(path, number, row, col) if col >= first else math.nan for col in range(width)])
        where.append(f"line {number}")
    return _Table(
        columns=columns,
        frames=np.array(frames, dtype=np.int64),
        values=np.array(values, dtype=float).reshape(len(values), width),
        where=where,
    )


_EXPORT_AGAIN = "export it again (DeepLabCut's .h5 or CSV, or SLEAP's analysis HDF5)"


def _opens_as_hdf5(path: Path) -> bool:
    """Whether HDF5 itself can open `path` and read every object's attributes (whatever the file holds). PyTables
    reads a damaged attribute natively and can crash the process (a cut or overwritten string attribute: a
    segmentation fault), where h5py raises."""
    import h5py

    def attributes(_name: str, item: h5py.HLObject) -> None:
        for key in item.attrs:
            item.attrs[key]  # read, to find a damaged one

    try:
        with h5py.File(path, "r") as f:
            attributes("/", f)
            f.visititems(attributes)
            return True
    except Exception:  # h5py raises OSError, RuntimeError, KeyError, ... for a damaged file
        return False


def _h5_contents(path: Path, tables: list[str]) -> str:
    """What an HDF5 file without DeepLabCut's table holds, for the message: its pandas tables, else its top-level
    groups and datasets (a JABS pose file holds `poseest`)."""
    if tables:
        return f"keys: {', '.join(tables)}"
    import h5py

    try:
        with h5py.File(path, "r") as f:
            names = list(f.keys())
    except Exception:  # h5py raises many types for a damaged file: the message lists what it can
        names = []
    jabs = " (a JABS pose file?)" if "poseest" in names else ""
    return f"no pandas table; top level: {', '.join(names[:8]) or 'nothing'}{jabs}"


def _read_h5(path: Path) -> _Table:
    """DLC's .h5: a pandas table (PyTables), read with pandas."""
    try:
        import pandas as pd
    except ImportError:
        raise InputError(
            path, "reading DeepLabCut .h5 needs pandas and tables", fix="pip install pandas tables, or import DLC's CSV"
        ) from None
    if not path.is_file():
        raise InputError(path, "file not found" if not path.exists() else "not a file")
    if not _opens_as_hdf5(path):  # before PyTables, which may crash on it
        raise InputError(path, "not a readable HDF5 file: damaged or truncated", fix=_EXPORT_AGAIN)
    try:
        with pd.HDFStore(path, mode="r") as store:
            keys = [k.lstrip("/") for k in store.keys()]  # noqa: SIM118 (an HDFStore)
            key = next((k for k in H5_KEYS if k in keys), keys[0] if len(keys) == 1 else None)
            if key is None:
                raise InputError(
                    path,
                    f"no DeepLabCut table in it ({_h5_contents(path, keys)})",
                    fix=f"DeepLabCut writes its points under {' or '.join(H5_KEYS)}; another tool's points: export "
                    "them as tracks.csv (video, frame, point, x, y; docs/formats.md)",
                )
            frame = store[key]
    except InputError:
        raise
    except ImportError:
        raise InputError(path, "reading DeepLabCut .h5 needs the tables package", fix="pip install tables") from None
    except Exception as error:  # PyTables raises many types for an HDF5 file that is not pandas'
        raise InputError(
            path, f"not a readable pandas HDF5 file ({type(error).__name__})", fix="give DeepLabCut's .h5 or its CSV"
        ) from None
    if not isinstance(frame, pd.DataFrame):
        raise InputError(path, f"{key!r} holds a {type(frame).__name__}, not DeepLabCut's table", fix=_FIX)
    names = [str(n).lower() if n is not None else "" for n in frame.columns.names]
    if "coords" not in names or "bodyparts" not in names:
        raise InputError(path, f"table {key!r} has column levels {names}, not DeepLabCut's", fix=_FIX)
    header = {name: ["", *(str(c[level]) for c in frame.columns)] for level, name in enumerate(names) if name}
    columns = {k: {c: col - 1 for c, col in cols.items()} for k, cols in _columns(path, header, 1, key).items()}
    try:
        values = frame.to_numpy(dtype=float)
    except (TypeError, ValueError):
        raise InputError(
            path, f"table {key!r} holds values that are not numbers", fix="give DeepLabCut's .h5"
        ) from None
    where = [f"row {r + 1}" for r in range(len(frame))]
    infinite = np.argwhere(np.isinf(values))
    if infinite.size:  # as in the CSV: a corrupt value, not an undetected point
        r, c = (int(i) for i in infinite[0])
        raise InputError(
            path,
            f"table {key!r} column {c + 1} holds {values[r, c]} (not a finite number)",
            where=where[r],
            fix="store NaN where the point was not detected",
        )
    frames = []
    for r, label in enumerate(frame.index):
        cells = [str(c) for c in label] if isinstance(label, tuple) else [str(label)]
        frames.append(_frame_of(path, where[r], cells))
    return _Table(columns=columns, frames=np.array(frames, dtype=np.int64), values=values, where=where)


def _frame_of(path: Path, where: str, index_cells: list[str]) -> int:
    text = " ".join(c.strip() for c in index_cells if c.strip())
    if _NUMBER.fullmatch(text):  # an index, not an image name: -7 or 2.0 are refused, not read as 7 or 0
        return parse_frame(text, path, where)
    # The image's own name holds the frame: a number of its folder (a date) is not one.
    image = re.split(r"[/\\]", [c.strip() for c in index_cells if c.strip()][-1])[-1] if text else ""
    match = _LAST_NUMBER.search(image)
    if match is None:
        raise InputError(
            path,
            f"cannot tell the frame number from {shown(image or text)}",
            where=where,
            fix="the first column must be the frame index or an image name ending in a number",
        )
    return parse_frame(match.group(1), path, where)


def _number(path: Path, number: int, row: list[str], col: int) -> float:
    if col >= len(row):
        raise InputError(path, f"expected at least {col + 1} fields, found {len(row)}", where=f"line {number}")
    cell = row[col].strip()
    if not cell:
        return math.nan
    try:
        value = float(cell)
    except ValueError:
        raise InputError(path, f"{cell!r} in column {col + 1} is not a number", where=f"line {number}") from None
    if math.isinf(value):  # not an empty cell: a corrupt value, which would otherwise vanish unseen
        raise InputError(
            path,
            f"{cell!r} in column {col + 1} is not a finite number",
            where=f"line {number}",
            fix="leave the cell empty where the point was not detected",
        )
    return value
