"""The smoothing spline's banded system (reconstruct/trajectory.py, reconstruct/clock_polish.py): the distinct
instants of the capture times, the prior's bands, the rays' data blocks and their sums per instant.

Unknowns are the positions at the instants, three coordinates each (unknown 3i + k); the prior links the same
coordinate of instants i-2..i+2, so every system is banded with BANDS lower bands (scipy's `cholesky_banded` lower
form) and block-banded with 3x3 blocks (reconstruct/block_inverse.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruct.block_inverse import BANDS

PRIOR_DIAGONALS = (0, 3, 6)  # the prior's nonzero bands: it links the same coordinate of nodes i-2..i+2
# Capture times closer than this fraction of tau are one instant (one position), so that a pair of nearly
# concurrent frames cannot make the system ill-conditioned.
MERGE_FRACTION = 0.01


@dataclass(frozen=True)
class TimeNodes:
    node_of_frame: np.ndarray  # (F,) index of the frame's instant
    times: np.ndarray  # (n,) increasing
    tau: float  # median spacing of consecutive distinct instants


def time_nodes(times: np.ndarray, merge_fraction: float = MERGE_FRACTION, tau: float | None = None) -> TimeNodes:
    """Distinct instants of `times (F,)`; gaps below merge_fraction x the median gap join one instant. `tau`
    fixes the time unit (else the median gap between instants)."""
    order = np.argsort(times, kind="stable")
    sorted_times = times[order]
    gaps = np.diff(sorted_times)
    positive = gaps[gaps > 0]
    unit = tau if tau is not None else (float(np.median(positive)) if positive.size else 1.0)
    new_node = np.concatenate([[True], gaps > merge_fraction * unit])
    node_sorted = np.cumsum(new_node) - 1
    node_of_frame = np.empty(len(times), dtype=np.int64)
    node_of_frame[order] = node_sorted
    counts = np.bincount(node_sorted)
    node_times = np.bincount(node_sorted, weights=sorted_times) / counts
    node_gaps = np.diff(node_times)
    if tau is None:
        tau = float(np.median(node_gaps)) if node_gaps.size else 1.0
    return TimeNodes(node_of_frame=node_of_frame, times=node_times, tau=tau)


def prior_bands(nodes: TimeNodes) -> np.ndarray:
    """(BANDS, 3n) lower banded form of sum_i a_i D2_i^T D2_i (kron I3), time in units of tau."""
    n = len(nodes.times)
    bands = np.zeros((BANDS, 3 * n))
    if n < 3:
        return bands
    t = nodes.times / nodes.tau
    h = np.diff(t)  # (n-1,)
    h0, h1 = h[:-1], h[1:]  # gaps before and after interior node i = 1..n-2
    span = h0 + h1
    # Second divided difference 2 / (h0 + h1) * ((Y+ - Y) / h1 - (Y - Y-) / h0).
    coef = np.stack([2 / (span * h0), -2 / (h0 * h1), 2 / (span * h1)], axis=1)  # (n-2, 3) for i-1, i, i+1
    area = span / 2
    for a in range(3):
        for b in range(a + 1):
            value = area * coef[:, a] * coef[:, b]  # M[i-1+a, i-1+b], a >= b
            rows = np.arange(n - 2) + b  # the column node (lower form: column index)
            for k in range(3):
                bands[3 * (a - b), 3 * rows + k] += value  # distinct columns: add.at's sums
    return bands


def data_blocks(
    rays: np.ndarray, centers: np.ndarray, weight: np.ndarray, node: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Sum over observations of weight (I - r r^T) per node, (n, 3, 3), and the right-hand sides, (n, 3)."""
    projector = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]  # (m, 3, 3)
    blocks = weight[:, None, None] * projector
    rhs = np.einsum("mij,mj->mi", blocks, centers)
    return sum_at(node, blocks, n), sum_at(node, rhs, n)


def sum_at(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """(size, ...) sums of `values (m, ...)` by `index (m,)`: np.add.at's sums in its order, by np.bincount, which
    is many times faster."""
    flat = values.reshape(len(values), -1)
    width = flat.shape[1]
    slots = (index[:, None] * width + np.arange(width)).ravel()
    return np.bincount(slots, weights=flat.ravel(), minlength=size * width).reshape(size, *values.shape[1:])


def sum_at_slots(index: np.ndarray, padded: np.ndarray, size: int, alone: np.ndarray) -> np.ndarray:
    """`sum_at(index, padded[:-1], size)`, bitwise, for values `padded (m + 1, ...)` whose last row is zeros;
    `alone (m,)` marks the values that are the only one of their slot: those are gathered (then + 0.0, bincount's
    first sum), only the others summed by bincount. With unsynchronized cameras nearly every instant holds one
    frame, so nearly every sum has one term, and a gather is several times faster than a scatter or bincount."""
    m = len(padded) - 1
    source = np.full(size, m)  # empty slots take the zero row
    source[index[alone]] = np.flatnonzero(alone)
    out = padded.take(source, axis=0)
    out += 0.0  # 0.0 + x: a gathered -0.0 becomes +0.0 as in bincount
    if not alone.all():
        rest = index[~alone]
        out[rest] = sum_at(rest, padded[:m][~alone], size)[rest]  # the others' slots hold no gathered value
    return out


def zero_row(values: np.ndarray) -> np.ndarray:
    """`values (m, ...)` with a row of zeros appended, (m + 1, ...)."""
    return np.concatenate([values, np.zeros((1, *values.shape[1:]))])


# The lower triangle of a symmetric 3x3 block, (row, column) pairs, and the positions of its diagonal among them.
LOWER = ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2))
LOWER_DIAGONAL = (0, 2, 5)


def add_blocks(bands: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Banded matrix + block diagonal (n, 3, 3) (lower form)."""
    out = bands.copy()
    columns = out.reshape(BANDS, len(blocks), 3)  # a view: column 3i + col is [:, i, col]
    for row in range(3):
        for col in range(row + 1):
            columns[row - col, :, col] += blocks[:, row, col]
    return out


def prior_value(bands: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y^T M y for the lower-banded prior M (BANDS, N) of `prior_bands` and y (..., N); its other bands are zero,
    and their terms would add exact zeros."""
    value = np.sum(bands[0] * y * y, axis=-1)
    for d in PRIOR_DIAGONALS[1:]:
        value = value + 2.0 * np.sum(bands[d, :-d] * y[..., :-d] * y[..., d:], axis=-1)
    return value
