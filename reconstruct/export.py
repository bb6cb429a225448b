"""Exports for biomechanics tools: OpenSim TRC and C3D, one row per reconstructed frame in a global order.

The frames of unsynchronized videos have no common clock. Until the solver recovers one, the global order is
taken from the decoder times of cameras.json when every frame has one (exact within a video, but it assumes the
videos started together: the offsets between videos are unknown), else from the solver's sequencing (a spectral
ordering of the self-expression graph: frames that express each other are close in time; the order is local and
the spacing between rows is not measured). Either way the rows are evenly spaced at `rate_hz` in the file, so the
time axis of an export is nominal; `TIMING_NOTE` says so inside the C3D file and docs/formats.md for TRC (whose
header has no room for comments).
"""

from __future__ import annotations

import enum
import logging
import tempfile
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, laplacian

from dynrecon.atomic import atomic_open
from dynrecon.errors import InputError
from reconstruct.mocap import UNIT_TO_MM, Mocap, write_trc
from reconstruct.points import FramePoints, Sequencing
from sfm.cameras import CameraSet

log = logging.getLogger(__name__)

TIMING_NOTE = ("dynrecon: rows are frames of unsynchronized videos in an estimated global order, evenly spaced "
               "at the file rate; the true spacing (and, with decoder times, the start offsets between videos) "
               "is unknown")


class OrderSource(enum.Enum):
    TIME = "time"  # decoder times of cameras.json (videos assumed to start together)
    SEQUENCING = "sequencing"  # spectral order of the solver's self-expression graph
    FILE = "file"  # the order of points3d.csv (neither of the above available)


def frame_times(points: FramePoints, cameras: CameraSet) -> np.ndarray | None:
    """(F,) decoder time of every frame of `points`, or None when any frame lacks one."""
    known = {(v.name, f.frame): f.time for v in cameras.videos for f in v.frames}
    times = [known.get((video, int(frame))) for video, frame in zip(points.videos, points.frames, strict=True)]
    if any(t is None for t in times):
        return None
    return np.array(times, dtype=float)


def sequencing_order(points: FramePoints, sequencing: Sequencing) -> np.ndarray:
    """(F,) frame indices of `points` sorted along the Fiedler vector of the symmetrized W graph.

    The direction is chosen so that frame numbers increase within videos on average. Frames the graph does not
    connect to the largest component keep their file order after it.
    """
    index = points.index()
    rows, cols, vals = [], [], []
    for i, (video, frame) in enumerate(zip(sequencing.videos, sequencing.frames, strict=True)):
        target = index.get((video, int(frame)))
        if target is None:
            continue
        for j, w in zip(sequencing.neighbours[i], sequencing.weights[i], strict=True):
            source = index.get((sequencing.videos[int(j)], int(sequencing.frames[int(j)])))
            if source is not None and w > 0:
                rows.append(target)
                cols.append(source)
                vals.append(float(w))
    F = points.num_frames
    # Consecutive frames of one video are neighbours in time too: link them so each video stays a chain.
    for a in range(F):
        for b in range(a + 1, min(F, a + 2)):
            if points.videos[a] == points.videos[b]:
                rows.append(a)
                cols.append(b)
                vals.append(0.5)
    graph = coo_matrix((vals, (rows, cols)), shape=(F, F)).tocsr()
    graph = graph + graph.T
    _, component = connected_components(graph, directed=False)
    main = np.flatnonzero(component == np.bincount(component).argmax())
    if len(main) < 3:
        return np.arange(F)
    sub = graph[main][:, main].toarray()
    _, vectors = np.linalg.eigh(laplacian(sub))
    fiedler = vectors[:, 1]
    trend = 0.0
    for video in set(points.videos):
        members = np.array([k for k, i in enumerate(main) if points.videos[i] == video])
        if len(members) > 1:
            trend += float(np.corrcoef(points.frames[main[members]], fiedler[members])[0, 1])
    if trend < 0:
        fiedler = -fiedler
    rest = np.setdiff1d(np.arange(F), main)
    return np.concatenate([main[np.argsort(fiedler, kind="stable")], rest])


def global_order(points: FramePoints, cameras: CameraSet | None = None,
                 sequencing: Sequencing | None = None) -> tuple[np.ndarray, OrderSource]:
    """(F,) frame indices of `points` in the best global order available, and where it came from."""
    times = frame_times(points, cameras) if cameras is not None else None
    if times is not None:
        # Ties (two videos at the same decoder time) keep the file's video order.
        return np.lexsort((np.arange(points.num_frames), times)), OrderSource.TIME
    if sequencing is not None:
        return sequencing_order(points, sequencing), OrderSource.SEQUENCING
    return np.arange(points.num_frames), OrderSource.FILE


def _ordered(points: FramePoints, order: np.ndarray | None) -> np.ndarray:
    """(N, P, 3) positions in `order` (None: file order); checks that `order` indexes frames."""
    if order is None:
        return points.xyz
    order = np.asarray(order)
    if order.ndim != 1 or not np.issubdtype(order.dtype, np.integer) or \
            (order.size and (order.min() < 0 or order.max() >= points.num_frames)):
        raise InputError(None, f"export order must be frame indices in [0, {points.num_frames}), got {order!r}")
    return points.xyz[order]


def _check_rate_units(rate_hz: float, units: str) -> None:
    if not (rate_hz > 0 and np.isfinite(rate_hz)):
        raise InputError(None, f"export rate must be a positive number of Hz, got {rate_hz}")
    if units not in UNIT_TO_MM:
        raise InputError(None, f"unknown export units {units!r}", fix=f"use one of {', '.join(UNIT_TO_MM)}")


def write_trc_export(points: FramePoints, order: np.ndarray | None, rate_hz: float, path: str | Path, *,
                     units: str = "mm") -> Path:
    """OpenSim TRC: row k = frame order[k] at time k / rate_hz; positions as stored (in `units`), empty = NaN."""
    _check_rate_units(rate_hz, units)
    xyz = _ordered(points, order)
    mocap = Mocap(xyz=xyz * UNIT_TO_MM[units], rate=float(rate_hz), marker_names=list(points.point_names),
                  times=np.arange(len(xyz)) / float(rate_hz))
    return write_trc(path, mocap, units=units)


def write_c3d_export(points: FramePoints, order: np.ndarray | None, rate_hz: float, path: str | Path, *,
                     units: str = "mm") -> Path:
    """C3D (via ezc3d): POINT data in `order` at `rate_hz`, NaN = invalid sample; a DYNRECON parameter group
    keeps the timing note and the source (video, frame) of every row."""
    import ezc3d  # compiled; imported here so the rest of the package works without it

    _check_rate_units(rate_hz, units)
    xyz = _ordered(points, order)
    rows = np.arange(points.num_frames) if order is None else np.asarray(order)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(rate_hz)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(points.point_names)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = [units]
    data = np.ones((4, len(points.point_names), len(xyz)))
    data[:3] = xyz.transpose(2, 1, 0)
    c3d["data"]["points"] = data
    c3d.add_parameter("DYNRECON", "TIMING", [TIMING_NOTE])
    c3d.add_parameter("DYNRECON", "VIDEOS", [points.videos[int(i)] for i in rows])
    c3d.add_parameter("DYNRECON", "FRAMES", [int(points.frames[int(i)]) for i in rows])
    path = Path(path)
    # ezc3d writes to a path; write a scratch copy and publish it atomically (readers never see half a file).
    with tempfile.TemporaryDirectory(prefix=".c3d-", dir=path.parent if path.parent.is_dir() else None) as scratch:
        scratch_file = Path(scratch) / "export.c3d"
        c3d.write(str(scratch_file))
        with atomic_open(path, "wb") as handle:
            handle.write(scratch_file.read_bytes())
    return path
