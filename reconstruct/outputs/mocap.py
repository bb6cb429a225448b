"""Motion-capture marker trajectories (C3D, TRC) as ground truth for the simulation protocol.

Everything is converted to millimetres. A missing sample is NaN: files store gaps as NaN, as (0, 0, 0) or
(C3D) as a negative residual, and all three are masked here so that a gap never passes for a position at the
origin.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import InputError

log = logging.getLogger(__name__)

SUFFIXES = (".c3d", ".trc")
MAX_MM = 1e9  # a marker this far from the origin (1000 km) is a corrupt value, not a motion
UNIT_TO_MM = {
    "mm": 1.0,
    "millimeters": 1.0,
    "millimetres": 1.0,
    "cm": 10.0,
    "centimeters": 10.0,
    "centimetres": 10.0,
    "m": 1000.0,
    "meters": 1000.0,
    "metres": 1000.0,
}
# POINT groups that list model outputs stored as points (Vicon Plug-in Gait: joint angles in degrees, forces,
# moments, powers): not marker positions
MODEL_OUTPUTS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")
# frames read wrong (a misplaced data section) jump back and forth: a median speed no body reaches, and second
# differences far over half the two-frame step (white noise gives about 3.5) -- a fast single object moves smoothly
MISREAD_SPEED_MM_S = 10_000.0
MISREAD_JAGGED = 5.0


@dataclass(kw_only=True)
class Mocap:
    """Marker trajectories sampled at a constant rate.

    `xyz[k]` is the sample at `times[k]` seconds (the file's own clock); NaN marks a missing sample. Windows
    and cleaning keep `times` exact, so a capture time is always `times[k]` even after frames were dropped.
    """

    xyz: np.ndarray  # (T, M, 3) millimetres, NaN = missing
    rate: float  # Hz of the original sampling (before any window step)
    marker_names: list[str]  # (M,) unique, non-empty
    times: np.ndarray  # (T,) seconds
    path: Path | None = None

    @property
    def num_frames(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def num_markers(self) -> int:
        return int(self.xyz.shape[1])

    def missing(self) -> np.ndarray:
        """(T, M) bool: the sample is missing."""
        return np.isnan(self.xyz).any(axis=2)


def read_mocap(path: str | Path) -> Mocap:
    """Read a `.c3d` or `.trc` file into millimetres with NaN gaps; any problem is a one-line InputError."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(
            path, f"unknown motion-capture format {path.suffix or '(no extension)'!r}", fix="give a .c3d or .trc file"
        )
    if not path.is_file():
        raise InputError(path, "file not found", fix="give the path of a .c3d or .trc file")
    mocap = _read_c3d(path) if suffix == ".c3d" else _read_trc(path)
    if mocap.num_markers == 0:
        raise InputError(path, "the file has no markers", fix="give a file with 3D marker trajectories")
    if mocap.num_frames == 0:
        raise InputError(path, "the file has no frames", fix="give a file with at least one frame")
    if not (math.isfinite(mocap.rate) and mocap.rate > 0):
        raise InputError(path, f"invalid sampling rate {mocap.rate!r}", fix="the point rate must be positive")
    if mocap.missing().all():
        raise InputError(path, "every sample is missing (all zero or NaN)")
    if suffix == ".c3d":  # a binary layout the reader can misplace (a text file's rows cannot shift so)
        _check_motion(mocap, path)
    return mocap


def unit_scale(units: str) -> float | None:
    """Millimetres per unit of a file's units label, None when unknown; a label cut short by its writer ('mete',
    'milli') counts as the unit it begins."""
    label = units.strip().lower()
    if label in UNIT_TO_MM:
        return UNIT_TO_MM[label]
    if len(label) < 3:
        return None
    whole = ("millimeters", "millimetres", "centimeters", "centimetres", "meters", "metres")
    found = {UNIT_TO_MM[name] for name in whole if name.startswith(label)}
    return found.pop() if len(found) == 1 else None


def _check_motion(mocap: Mocap, path: Path) -> None:
    """Refuse trajectories whose frames were evidently not read as written (one line), rather than simulate them."""
    if mocap.num_frames < 3:
        return
    x = mocap.xyz
    with np.errstate(invalid="ignore"):
        step = np.linalg.norm(np.diff(x, axis=0), axis=2)
        turn = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=2)
        span = np.linalg.norm(x[2:] - x[:-2], axis=2) / 2
    if not (np.isfinite(step).any() and np.isfinite(turn).any()):
        return
    speed = float(np.nanmedian(step)) * mocap.rate
    jagged = float(np.nanmedian(turn)) / max(float(np.nanmedian(span)), 1e-9)
    if speed > MISREAD_SPEED_MM_S and jagged > MISREAD_JAGGED:
        raise InputError(
            path,
            f"the markers jump back and forth between frames (median {speed / 1000:.0f} m/s): the file's frames are "
            "not read as they were written (a C3D whose data section the reader misplaces), or its labels change "
            "from frame to frame",
            fix="export the trial again from the capture software (or as .trc), and check it in a viewer",
        )


def _unique_names(names: list[str], count: int) -> list[str]:
    """Blank labels become M<index>; repeated labels get a #2, #3 suffix, so names stay usable as ids."""
    result: list[str] = []
    seen: dict[str, int] = {}
    for index in range(count):
        name = names[index].strip() if index < len(names) else ""
        name = name or f"M{index}"
        if name in seen:
            seen[name] += 1
            name = f"{name}#{seen[name]}"
        else:
            seen[name] = 1
        result.append(name)
    return result


def _mask_gaps(xyz: np.ndarray) -> np.ndarray:
    """Set samples that are exactly (0, 0, 0) or partly non-finite to NaN, in place; returns xyz."""
    gap = (~np.isfinite(xyz)).any(axis=2) | (xyz == 0).all(axis=2)
    xyz[gap] = np.nan
    return xyz


# ------------------------------------------------------------------------------------------------------------
# C3D


def _read_c3d(path: Path) -> Mocap:
    import ezc3d  # compiled reader; imported here so the TRC path works without it

    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as error:  # ezc3d raises bare RuntimeError/IOError subclasses on corrupt files
        what, fix = _unreadable(str(error).strip() or type(error).__name__)
        raise InputError(path, what, fix=fix) from None
    point = c3d["parameters"].get("POINT", {})
    points = np.asarray(c3d["data"]["points"], dtype=float)  # (4, M, T)
    if points.ndim != 3 or points.shape[1] == 0:
        raise InputError(path, "the file has no markers", fix="give a file with 3D marker trajectories")
    declared = _c3d_header_frames(path)
    if declared is not None and points.shape[2] < declared:  # ezc3d reads what is there and says nothing
        raise InputError(
            path,
            f"its header declares {declared} frames but only {points.shape[2]} could be read (the file may be "
            "truncated)",
            fix="check that the file is complete",
        )
    xyz = np.ascontiguousarray(points[:3].transpose(2, 1, 0))  # (T, M, 3)
    residuals = c3d["data"].get("meta_points", {}).get("residuals")
    if residuals is not None and np.shape(residuals)[1:] == (xyz.shape[1], xyz.shape[0]):
        # A negative residual is C3D's own "invalid sample" flag (ezc3d usually already returns NaN there).
        xyz[np.asarray(residuals)[0].T < 0] = np.nan
    _mask_gaps(xyz)

    labels: list[str] = []
    # C3D splits long label lists into LABELS2, LABELS3, ...
    for key in ("LABELS", *(f"LABELS{i}" for i in range(2, 10))):
        if key in point:
            labels.extend(str(v) for v in point[key]["value"])
    names = _unique_names(labels, xyz.shape[1])
    outputs = {str(v).strip() for key in MODEL_OUTPUTS if key in point for v in point[key]["value"]} - {""}
    keep = [m for m, label in enumerate(labels[: xyz.shape[1]]) if label.strip() not in outputs]
    keep += list(range(len(labels), xyz.shape[1]))  # points without a label are no listed output
    if len(keep) < xyz.shape[1]:
        kept = set(keep)
        dropped = [names[m] for m in range(xyz.shape[1]) if m not in kept]
        log.warning(
            "%s: %d of its %d points are model outputs (POINT:%s: joint angles, forces, moments, powers), not "
            "markers: left out (%s)",
            path,
            len(dropped),
            xyz.shape[1],
            "/".join(key for key in MODEL_OUTPUTS if key in point),
            ", ".join(dropped[:6]) + (", ..." if len(dropped) > 6 else ""),
        )
        xyz, names = xyz[:, keep], [names[m] for m in keep]
    units = _c3d_value(point, "UNITS", "mm")
    scale = unit_scale(str(units))
    if scale is None:
        raise InputError(path, f"unknown POINT:UNITS {units!r}", fix="expected mm, cm or m")
    xyz *= scale
    far = np.argwhere(np.abs(xyz) > MAX_MM)
    if len(far):
        t, m, k = far[0]
        raise InputError(path, _implausible(float(xyz[t, m, k]) / scale, str(units)), where=f"frame {t} {names[m]}")

    rate = float(str(_c3d_value(point, "RATE", c3d["header"]["points"].get("frame_rate", 0.0))))
    first = int(c3d["header"]["points"].get("first_frame", 0))
    times = (first + np.arange(xyz.shape[0])) / rate if rate > 0 else np.arange(xyz.shape[0], dtype=float)
    return Mocap(xyz=xyz, rate=rate, marker_names=names, times=times, path=path)


def _unreadable(said: str) -> tuple[str, str]:
    """What the reader's failure means for the user, and what to do."""
    if "MIPS" in said:
        return (
            "a big-endian (SGI / MIPS) C3D file, which the C3D reader does not read",
            "convert it to a PC (Intel) C3D or a .trc file (e.g. in Mokka or the capture software)",
        )
    if "ignoreBadFormatting" in said or "not an INT" in said or "Parameter type" in said:
        return (
            f"its parameter section is malformed for the C3D reader ({said.split(';')[0].split('.')[0]})",
            "export the trial again from the capture software, or convert it to a .trc file",
        )
    return f"not a readable C3D file ({said})", "check that the file is complete"


def _implausible(value: float, units: str) -> str:
    return f"coordinate {value:.6g} {units.strip()} is implausible (over {MAX_MM / 1e6:g} km from the origin)"


def _c3d_header_frames(path: Path) -> int | None:
    """The frame count of the file's own header (words 4 and 5: first and last frame), as written: ezc3d rewrites
    its parsed header to the frames it could read. None where the header does not tell (a count past its 16 bits)."""
    with path.open("rb") as handle:
        head = handle.read(512)
        parameters = head[0] if head else 0
        handle.seek(max(parameters - 1, 0) * 512 + 3)
        processor = handle.read(1)
    if len(head) < 10 or not processor:
        return None
    order = ">" if processor[0] == 86 else "<"  # 84 Intel and 85 DEC store little-endian integers, 86 MIPS big
    first, last = struct.unpack(order + "HH", head[6:10])
    if last == 0xFFFF or last < first:
        return None
    return last - first + 1


def _c3d_value(group: dict, key: str, default: object) -> object:
    values = group.get(key, {}).get("value")
    if values is None or len(values) == 0:
        return default
    return values[0]


# ------------------------------------------------------------------------------------------------------------
# TRC (OpenSim): line 1 PathFileType, line 2 header keys, line 3 their values, line 4 marker names,
# line 5 X1 Y1 Z1, data after it: Frame#, Time, X1, Y1, Z1, ...


def _read_trc(path: Path) -> Mocap:
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # Windows exports put non-UTF-8 paths in line 1
    lines = text.splitlines()
    if len(lines) < 5:
        raise InputError(
            path, f"only {len(lines)} line(s); a TRC file has 5 header lines", fix="check that the file is complete"
        )
    # OpenSim writes tabs; some tools (pyomeca's test files, spreadsheet exports) write commas, padded with empty
    # columns to the data's width.
    separator = "," if "\t" not in lines[1] and "," in lines[1] else "\t"
    # Columns of lines 2-3 are padded with extra tabs in some exports: pair the non-empty tokens instead.
    keys = lines[1].replace(separator, " ").split()
    values = lines[2].replace(separator, " ").split()
    header = dict(zip(keys, values, strict=False))
    try:
        rate = float(header["DataRate"])
        declared_markers = int(float(header["NumMarkers"]))
        declared_frames = int(float(header["NumFrames"]))
    except (KeyError, ValueError):
        raise InputError(
            path, "lines 2-3 lack DataRate, NumFrames or NumMarkers", where="line 3", fix="see the OpenSim TRC format"
        ) from None
    units = header.get("Units", "mm")
    scale = unit_scale(units)
    if scale is None:
        raise InputError(path, f"unknown Units {units!r}", where="line 3", fix="expected mm, cm or m")
    # Marker names follow Frame# and Time; their column spacing varies between exporters: keep the order only.
    names = [n.strip() for n in lines[3].split(separator)[2:] if n.strip()]
    if declared_markers == 0 or not names:
        raise InputError(path, "the file has no markers", where="line 4")
    if len(names) != declared_markers:
        raise InputError(
            path,
            f"line 4 names {len(names)} markers but NumMarkers is {declared_markers}",
            where="line 4",
            fix="make the marker names and NumMarkers agree",
        )
    width = 2 + 3 * declared_markers
    rows: list[list[float]] = []
    first_time = math.nan
    for number, line in enumerate(lines[5:], start=6):
        if not line.replace(separator, "").strip():  # blank, or empty columns only (commas)
            continue
        fields = line.split(separator)
        if len(fields) < width:
            raise InputError(
                path,
                f"expected {width} {'comma' if separator == ',' else 'tab'}-separated fields, found {len(fields)}",
                where=f"line {number}",
                fix="the file may be truncated",
            )
        if any(f.strip() for f in fields[width:]):
            raise InputError(
                path, f"more than {width} fields", where=f"line {number}", fix="make the columns agree with NumMarkers"
            )
        try:
            values_row = [float(f) if f.strip() else math.nan for f in fields[2:width]]
            if not rows:
                first_time = float(fields[1]) if fields[1].strip() else math.nan
        except ValueError:
            raise InputError(path, "a coordinate is not a number", where=f"line {number}") from None
        if any(abs(v) * scale > MAX_MM for v in values_row):  # NaN compares False
            largest = max(values_row, key=lambda v: -1.0 if math.isnan(v) else abs(v))  # a gap (NaN) is no value
            raise InputError(path, _implausible(largest, units), where=f"line {number}")
        rows.append(values_row)
    if not rows:
        raise InputError(path, "the file has no frames", fix="data rows start on line 6")
    if len(rows) < declared_frames:
        raise InputError(
            path,
            f"NumFrames is {declared_frames} but only {len(rows)} data rows were found",
            fix="the file may be truncated",
        )
    xyz = _mask_gaps(np.array(rows, dtype=float).reshape(len(rows), declared_markers, 3)) * scale
    t0 = first_time if math.isfinite(first_time) else 0.0
    times = t0 + np.arange(len(rows)) / rate if rate > 0 else np.arange(len(rows), dtype=float)
    return Mocap(xyz=xyz, rate=rate, marker_names=_unique_names(names, declared_markers), times=times, path=path)


# ------------------------------------------------------------------------------------------------------------
# Writing TRC (tests, and handing a cleaned window to other tools)


def write_trc(path: str | Path, mocap: Mocap, *, units: str = "mm") -> Path:
    """Write an OpenSim TRC file (NaN samples as empty fields)."""
    path = Path(path)
    scale = UNIT_TO_MM[units]
    marker_count = mocap.num_markers
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{mocap.rate!r}\t{mocap.rate!r}\t{mocap.num_frames}\t{marker_count}\t{units}\t{mocap.rate!r}\t1\t"
        f"{mocap.num_frames}",
        "Frame#\tTime\t" + "\t\t\t".join(mocap.marker_names),
        "\t\t" + "\t".join(f"{axis}{i + 1}" for i in range(marker_count) for axis in "XYZ"),
        "",
    ]
    for k in range(mocap.num_frames):
        coords = (mocap.xyz[k] / scale).ravel()
        cells = ["" if not math.isfinite(v) else repr(float(v)) for v in coords]
        lines.append("\t".join([str(k + 1), repr(float(mocap.times[k])), *cells]))
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


# ------------------------------------------------------------------------------------------------------------
# Windows and cleaning


def select_window(mocap: Mocap, start: int = 0, length: int | None = None, step: int = 1) -> Mocap:
    """Samples `start, start + step, ...` below `start + length` (the file's own frames; None = to the end).

    `length` counts original frames, so a window covers the same stretch of motion at any `step`; `rate` stays
    the file's rate and `times` stays exact (the effective rate of the result is `rate / step`).
    """
    if step < 1:
        raise InputError(mocap.path, f"step must be >= 1, got {step}")
    if start < 0 or start >= mocap.num_frames:
        raise InputError(
            mocap.path,
            f"window start {start} is outside the file's {mocap.num_frames} frames",
            fix=f"use a start between 0 and {mocap.num_frames - 1}",
        )
    if length is not None and length < 1:
        raise InputError(mocap.path, f"window length must be >= 1, got {length}")
    stop = mocap.num_frames if length is None else min(mocap.num_frames, start + length)
    if length is not None and start + length > mocap.num_frames:
        log.info(
            "%s: window %d..%d runs past the last frame %d; using %d frames",
            mocap.path,
            start,
            start + length - 1,
            mocap.num_frames - 1,
            stop - start,
        )
    index = np.arange(start, stop, step)
    return replace(
        mocap, xyz=mocap.xyz[index].copy(), times=mocap.times[index].copy(), marker_names=list(mocap.marker_names)
    )


SPAN_SHARE = 0.9  # a frame of `complete_span` has at least this share of the most markers any frame has


def complete_span(mocap: Mocap) -> tuple[int, int] | None:
    """The first and last frame (0-based) of the longest run of frames that each hold at least SPAN_SHARE of the
    most markers present in any one frame; None when no frame holds a marker."""
    present = (~mocap.missing()).sum(axis=1)
    if not present.any():
        return None
    good = np.concatenate([[False], present >= SPAN_SHARE * present.max(), [False]])
    edges = np.flatnonzero(np.diff(good.astype(np.int8)))
    starts, stops = edges[0::2], edges[1::2]  # runs [start, stop)
    longest = int(np.argmax(stops - starts))
    return int(starts[longest]), int(stops[longest] - 1)


def drop_incomplete(mocap: Mocap, max_missing: float = 0.1, whole: Mocap | None = None) -> Mocap:
    """Keep only fully known samples, so a simulation never needs ground truth it does not have.

    1. Drop every marker missing in more than `max_missing` (a fraction) of the frames.
    2. Drop every frame where one of the kept markers is still missing. Capture times stay in `times`, so the
       remaining frames keep their true timing (a dropped frame shows up as a longer gap).
    Raises InputError when nothing is left; with `whole` (the file `mocap` is a window of) its fix names the
    file's longest stretch of frames where the markers are present together.
    """
    missing = mocap.missing()
    keep_markers = missing.mean(axis=0) <= max_missing
    fix = "choose another window or file"
    span = complete_span(whole) if whole is not None else None
    if span is not None:
        fix = f"the markers are present together in frames {span[0]}..{span[1]} of the file: --start {span[0]} "
        fix += f"--length {span[1] - span[0] + 1}"
    if not keep_markers.any():
        raise InputError(mocap.path, f"every marker is missing in more than {max_missing:.0%} of the frames", fix=fix)
    keep_frames = ~missing[:, keep_markers].any(axis=1)
    if not keep_frames.any():
        raise InputError(mocap.path, "no frame has all the usable markers", fix=fix)
    dropped_markers = [n for n, k in zip(mocap.marker_names, keep_markers, strict=True) if not k]
    if dropped_markers:  # a warning: the simulation's truth then lacks them, which -q would hide
        most = 2 * len(dropped_markers) > mocap.num_markers  # what is left may not be the motion the user meant
        log.warning(
            "%s: dropped %d of %d markers, missing in more than %.0f%% of the frames: %s%s",
            mocap.path,
            len(dropped_markers),
            mocap.num_markers,
            100 * max_missing,
            ", ".join(dropped_markers),
            f" (to keep more: --max-missing, or a window: {fix})" if most else "",
        )
    if not keep_frames.all():
        log.warning(
            "%s: dropped %d of %d frames with a missing marker", mocap.path, int((~keep_frames).sum()), mocap.num_frames
        )
    return replace(
        mocap,
        xyz=mocap.xyz[keep_frames][:, keep_markers].copy(),
        times=mocap.times[keep_frames].copy(),
        marker_names=[n for n, k in zip(mocap.marker_names, keep_markers, strict=True) if k],
    )
