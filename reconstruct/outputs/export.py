"""Exports for biomechanics tools: OpenSim TRC and C3D, in the global time the solver estimated.

The frames of unsynchronized videos have no common clock. When `dynrecon solve` recovered the videos' clocks
(sequencing.json, key `clocks`), every frame has a global time: the export resamples each trajectory on a uniform
grid of that clock at `rate_hz` (linear interpolation between reconstructed frames, never across a gap longer than
`MAX_GAP_FACTOR` frame periods of the fastest video), and `clock_note` states the clocks' median uncertainty.
Without clocks the order comes from the decoder times of cameras.json when every frame has one (exact within a
video, but it assumes the videos started together), else from the solver's sequencing (a spectral ordering of the
self-expression graph: local, and the spacing between rows is not measured); the rows are then frames, evenly
spaced at `rate_hz`, so the time axis is nominal, which `TIMING_NOTE` says inside the C3D file (docs/formats.md for
TRC, whose header has no room for comments).
"""

from __future__ import annotations

import enum
import logging
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, laplacian

from dynrecon.atomic import atomic_open
from dynrecon.errors import InputError
from reconstruct.outputs.mocap import UNIT_TO_MM, Mocap, write_trc
from reconstruct.outputs.points import SINGLE_VIEW, FramePoints, Sequencing
from sfm.cameras import CameraSet

log = logging.getLogger(__name__)

TIMING_NOTE = (
    "dynrecon: rows are frames of unsynchronized videos in an estimated global order, evenly spaced "
    "at the file rate; the true spacing (and, with decoder times, the start offsets between videos) "
    "is unknown"
)


MAX_GAP_FACTOR = 4.0


class OrderSource(enum.Enum):
    CLOCKS = "clocks"  # global times of the recovered video clocks (sequencing.json)
    TIME = "time"  # decoder times of cameras.json (videos assumed to start together)
    SEQUENCING = "sequencing"  # spectral order of the solver's self-expression graph
    FILE = "file"  # the order of points3d.csv (neither of the above available)


def frame_times(points: FramePoints, cameras: CameraSet) -> np.ndarray | None:
    """(F,) decoder time of every frame of `points`, or None when any frame lacks one."""
    return _times_of(points, {(v.name, f.frame): f.time for v in cameras.videos for f in v.frames})


def _times_of(points: FramePoints, known: dict[tuple[str, int], float | None]) -> np.ndarray | None:
    """(F,) the time `known` gives each (video, frame) of `points`, or None when some frame has none."""
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


def clock_times(points: FramePoints, sequencing: Sequencing | None) -> np.ndarray | None:
    """(F,) global time of every frame of `points` from the recovered clocks, or None when sequencing.json has no
    clocks or some frame has no global time (a video the clocks could not identify)."""
    if sequencing is None or not isinstance(sequencing.extra.get("clocks"), dict):
        return None
    try:
        known = {(str(e["video"]), int(e["frame"])): e["time"] for e in sequencing.extra["clocks"]["frames"]}
    except (KeyError, TypeError, ValueError):
        return None
    values = _times_of(points, known)
    return values if values is not None and np.all(np.isfinite(values)) else None


def clock_note(sequencing: Sequencing) -> str:
    """The timing note of an export resampled on the recovered clocks."""
    stds = [e.get("time_std") for e in sequencing.extra.get("clocks", {}).get("frames", [])]
    finite = [float(s) for s in stds if isinstance(s, int | float) and np.isfinite(s)]
    spread = f"{1000 * float(np.median(finite)):.1f} ms" if finite else "unknown"
    return (
        "dynrecon: rows are a uniform resampling of the trajectories on the global clock recovered from the "
        f"unsynchronized videos (median 1-sigma uncertainty of a frame's global time: {spread}); "
        "time 0 is the reference video's first frame"
    )


def resample_on_clock(points: FramePoints, times: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Trajectories on a uniform grid of the global clock: (xyz (N, P, 3), grid times (N,)).

    Frames at the same instant are averaged. A grid time gets a position only between two reconstructed frames no
    more than MAX_GAP_FACTOR median frame spacings apart (NaN otherwise: a gap is not bridged)."""
    times = np.asarray(times, dtype=float)
    if times.shape != (points.num_frames,) or not np.all(np.isfinite(times)):
        raise InputError(None, f"export times must be {points.num_frames} finite values")
    start = float(times.min())
    count = int(np.floor((float(times.max()) - start) * rate_hz + 1e-9)) + 1
    grid = start + np.arange(count) / rate_hz
    order = np.argsort(times, kind="stable")
    max_gap = MAX_GAP_FACTOR * _frame_period(points, times, rate_hz)
    P = len(points.point_names)
    xyz = np.full((count, P, 3), np.nan)
    for p in range(P):
        known = order[~np.isnan(points.xyz[order, p, 0])]
        if len(known) < 2:
            continue
        instants, inverse = np.unique(times[known], return_inverse=True)
        counts = np.bincount(inverse)
        values = np.stack([np.bincount(inverse, weights=points.xyz[known, p, k]) / counts for k in range(3)], axis=1)
        if len(instants) < 2:
            continue
        right = np.clip(np.searchsorted(instants, grid), 1, len(instants) - 1)
        left = right - 1
        inside = (grid >= instants[0]) & (grid <= instants[-1]) & (instants[right] - instants[left] <= max_gap)
        for k in range(3):
            column = np.interp(grid, instants, values[:, k])
            xyz[inside, p, k] = column[inside]
    return xyz, grid - start


def _frame_period(points: FramePoints, times: np.ndarray, rate_hz: float) -> float:
    """The fastest video's median step between its frames (seconds of the global clock)."""
    names = np.asarray(points.videos)
    steps = []
    for name in np.unique(names):
        own = np.sort(times[names == name])
        gaps = np.diff(own)
        gaps = gaps[gaps > 0]
        if gaps.size:
            steps.append(float(np.median(gaps)))
    return min(steps) if steps else 1.0 / rate_hz


def global_order(
    points: FramePoints, cameras: CameraSet | None = None, sequencing: Sequencing | None = None
) -> tuple[np.ndarray, OrderSource]:
    """(F,) frame indices of `points` in the best global order available, and where it came from."""
    clock = clock_times(points, sequencing)
    if clock is not None:
        return np.lexsort((np.arange(points.num_frames), clock)), OrderSource.CLOCKS
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
    if (
        order.ndim != 1
        or not np.issubdtype(order.dtype, np.integer)
        or (order.size and (order.min() < 0 or order.max() >= points.num_frames))
    ):
        raise InputError(None, f"export order must be frame indices in [0, {points.num_frames}), got {order!r}")
    return points.xyz[order]


def measured_only(points: FramePoints) -> FramePoints:
    """`points` without the positions fewer than two videos saw near their instant (points3d.csv `views`, where
    present): an export carries no flag, and such a position lies along one camera's rays at a depth nothing
    measured (reconstruct/views.py). They are gaps in the export, as a triangulation's would be."""
    views = points.extra.get("views")
    if views is None:
        return points
    single = (views < SINGLE_VIEW) & np.isfinite(points.xyz).all(axis=-1)
    if not single.any():
        return points
    counts = single.sum(axis=0)
    worst = ", ".join(f"{points.point_names[p]} {counts[p]}" for p in np.argsort(-counts)[:3] if counts[p])
    log.warning(
        "export: %d position(s) seen by fewer than %d videos near their instant are left out (gaps; most: %s)",
        int(single.sum()),
        SINGLE_VIEW,
        worst,
    )
    kept = replace(points, xyz=np.where(single[..., None], np.nan, points.xyz))
    emptied = np.isfinite(points.xyz).all(axis=-1).any(axis=0) & ~np.isfinite(kept.xyz).all(axis=-1).any(axis=0)
    if emptied.any():  # a whole trajectory gone: say so apart from the count
        log.warning(
            "export: no two videos ever saw %s near the same instant: %s empty in the export (points3d.csv keeps "
            "the solve's positions, flagged)",
            ", ".join(name for name, gone in zip(points.point_names, emptied.tolist(), strict=True) if gone),
            "it is" if emptied.sum() == 1 else "they are",
        )
    return kept


def check_units(units: str) -> None:
    """`--units` of run, batch and export, checked before any work: one of UNIT_TO_MM, else a one-line error."""
    if units not in UNIT_TO_MM:
        raise InputError(None, f"--units {units!r} is not a unit", fix=f"use one of {', '.join(UNIT_TO_MM)}")


def _check_rate_units(rate_hz: float, units: str) -> None:
    if not (rate_hz > 0 and np.isfinite(rate_hz)):
        raise InputError(None, f"export rate must be a positive number of Hz, got {rate_hz}")
    if units not in UNIT_TO_MM:
        raise InputError(None, f"unknown export units {units!r}", fix=f"use one of {', '.join(UNIT_TO_MM)}")


def write_trc_export(
    points: FramePoints,
    order: np.ndarray | None,
    rate_hz: float,
    path: str | Path,
    *,
    units: str = "mm",
    times: np.ndarray | None = None,
) -> Path:
    """OpenSim TRC: row k = frame order[k] at time k / rate_hz; positions as stored (in `units`), empty = NaN.
    With `times` (F,) global seconds (`clock_times`), rows are instead the uniform resampling on that clock."""
    _check_rate_units(rate_hz, units)
    points = measured_only(points)
    xyz = _ordered(points, order) if times is None else resample_on_clock(points, times, rate_hz)[0]
    mocap = Mocap(
        xyz=xyz * UNIT_TO_MM[units],
        rate=float(rate_hz),
        marker_names=list(points.point_names),
        times=np.arange(len(xyz)) / float(rate_hz),
    )
    return write_trc(path, mocap, units=units)


def write_c3d_export(
    points: FramePoints,
    order: np.ndarray | None,
    rate_hz: float,
    path: str | Path,
    *,
    units: str = "mm",
    times: np.ndarray | None = None,
    note: str = TIMING_NOTE,
) -> Path:
    """C3D (via ezc3d): POINT data in `order` at `rate_hz`, NaN = invalid sample; a DYNRECON parameter group
    keeps the timing note and the source (video, frame) of every row. With `times` (F,) global seconds the rows
    are the uniform resampling on that clock (`clock_note` for `note`) and carry no source frame."""
    import ezc3d  # compiled; imported here so the rest of the package works without it

    _check_rate_units(rate_hz, units)
    points = measured_only(points)
    if times is None:
        xyz = _ordered(points, order)
        rows = np.arange(points.num_frames) if order is None else np.asarray(order)
    else:
        xyz = resample_on_clock(points, times, rate_hz)[0]
        rows = np.zeros(0, dtype=np.int64)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(rate_hz)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(points.point_names)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = [units]
    data = np.ones((4, len(points.point_names), len(xyz)))
    data[:3] = xyz.transpose(2, 1, 0)
    c3d["data"]["points"] = data
    c3d.add_parameter("DYNRECON", "TIMING", [note])
    if len(rows):
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
