"""reconstruct.spline_system: instants, the prior's bands and the sums per instant of the refinement's system."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruct.block_inverse import BANDS
from reconstruct.spline_system import prior_bands, sum_at, sum_at_slots, time_nodes


def test_nearly_concurrent_times_merge_into_one_instant() -> None:
    nodes = time_nodes(np.array([0.0, 0.1, 0.1 + 1e-6, 0.2, 0.3]), merge_fraction=0.01)
    assert len(nodes.times) == 4
    assert nodes.node_of_frame[1] == nodes.node_of_frame[2]
    assert nodes.tau == pytest.approx(0.1, rel=1e-4)


def test_prior_is_the_second_difference_on_uniform_times() -> None:
    nodes = time_nodes(np.arange(6) * 0.25, merge_fraction=0.01)
    bands = prior_bands(nodes)
    n = 6
    D = np.zeros((n - 2, n))
    for i in range(n - 2):
        D[i, i : i + 3] = [1.0, -2.0, 1.0]
    expected = np.kron(D.T @ D, np.eye(3))
    dense = np.zeros((3 * n, 3 * n))
    for d in range(BANDS):
        idx = np.arange(3 * n - d)
        dense[idx + d, idx] = bands[d, : 3 * n - d]
        dense[idx, idx + d] = bands[d, : 3 * n - d]
    np.testing.assert_allclose(dense, expected, atol=1e-12)


def test_sums_at_slots_are_bincount_sums() -> None:
    rng = np.random.default_rng(0)
    index = rng.integers(0, 50, 200)
    values = rng.normal(size=(200, 3))
    values[:5] = -0.0
    alone = np.bincount(index, minlength=50)[index] == 1
    padded = np.concatenate([values, np.zeros((1, 3))])
    fast = sum_at_slots(index, padded, 50, alone)
    assert fast.tobytes() == sum_at(index, values, 50).tobytes()
