"""The GCV trace tr(M^-1 D) from the banded Cholesky factor, against the dense inverse."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import cholesky_banded

from reconstruct.block_inverse import BANDS, CHUNK, trace_of_inverse_times


def block_banded(rng: np.random.Generator, n: int) -> np.ndarray:
    """A random SPD matrix (3n, 3n) coupling instant i with i-2..i+2 (the refinement's structure)."""
    N = 3 * n
    A = rng.normal(size=(N, N))
    instant = np.arange(N) // 3
    near = np.abs(np.subtract.outer(instant, instant)) <= 2
    return np.where(near, (A + A.T) / 2, 0.0) + N * np.eye(N)


def lower_bands(M: np.ndarray) -> np.ndarray:
    bands = np.zeros((BANDS, len(M)))
    for d in range(min(BANDS, len(M))):
        bands[d, : len(M) - d] = np.diag(M, -d)
    return bands


@pytest.mark.parametrize("n", [1, 2, 3, 7, CHUNK, CHUNK + 5, 2 * CHUNK + 1])
def test_trace_matches_the_dense_inverse(n: int) -> None:
    rng = np.random.default_rng(n)
    systems = [block_banded(rng, n) for _ in range(3)]
    blocks = rng.normal(size=(3, n, 3, 3))
    factors = np.stack([cholesky_banded(lower_bands(M), lower=True) for M in systems])
    trace = trace_of_inverse_times(factors, blocks)
    for M, D, got in zip(systems, blocks, trace, strict=True):
        dense = np.zeros_like(M)
        for i in range(n):
            dense[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = D[i]
        assert got == pytest.approx(np.trace(np.linalg.solve(M, dense)), rel=1e-10, abs=1e-12)


def test_the_factor_corner_past_the_end_is_not_read() -> None:
    # LAPACK leaves the band's entries past the matrix's end undefined: garbage there changes nothing
    rng = np.random.default_rng(1)
    n = 9
    factor = cholesky_banded(lower_bands(block_banded(rng, n)), lower=True)
    blocks = rng.normal(size=(1, n, 3, 3))
    clean = trace_of_inverse_times(factor[None], blocks)
    dirty = factor.copy()
    for d in range(1, BANDS):
        dirty[d, 3 * n - d :] = 1e30
    np.testing.assert_array_equal(trace_of_inverse_times(dirty[None], blocks), clean)


def test_wrong_shapes_raise() -> None:
    with pytest.raises(ValueError, match="expected"):
        trace_of_inverse_times(np.zeros((1, BANDS, 7)), np.zeros((1, 2, 3, 3)))
