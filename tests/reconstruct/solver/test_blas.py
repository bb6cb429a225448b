"""The solve's BLAS thread limit: one thread inside, the caller's counts for the Anderson mix and afterwards."""

from __future__ import annotations

import pytest
import scipy.linalg  # noqa: F401  (loads scipy's own BLAS, which the limit must reach too)
from threadpoolctl import ThreadpoolController, threadpool_limits

from reconstruct.solver.blas import one_blas_thread, outer_blas_threads


def _blas_threads() -> list[int]:
    return [lib.num_threads for lib in ThreadpoolController().select(user_api="blas").lib_controllers]


def test_one_thread_inside_and_the_callers_count_outside() -> None:
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl controls")
    with threadpool_limits(2, user_api="blas"):
        before = _blas_threads()
        with one_blas_thread():
            assert _blas_threads() == [1] * len(before)
            with outer_blas_threads():
                assert _blas_threads() == before
            assert _blas_threads() == [1] * len(before)
        assert _blas_threads() == before


def test_outer_threads_outside_the_limit_change_nothing() -> None:
    before = _blas_threads()
    with outer_blas_threads():
        assert _blas_threads() == before
