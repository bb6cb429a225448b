"""The solve's BLAS thread limit: one thread inside, the caller's counts for the Anderson mix and afterwards."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import scipy.linalg  # noqa: F401  (loads scipy's own BLAS, which the limit must reach too)
from synthetic_motion import synthetic_problem
from threadpoolctl import ThreadpoolController, threadpool_limits

from reconstruct.solver import alternation
from reconstruct.solver.anderson import AndersonMixer
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


def test_the_solve_runs_on_one_thread_but_mixes_on_the_callers(monkeypatch: pytest.MonkeyPatch) -> None:
    if not _blas_threads():
        pytest.skip("no BLAS library that threadpoolctl controls")
    seen: dict[str, set[int]] = {"w_step": set(), "x_step": set(), "mix": set()}

    def recording(name: str, function: Callable[..., Any]) -> Callable[..., Any]:
        def wrapped(*args: Any, **kwargs: Any) -> Any:
            seen[name].update(_blas_threads())
            return function(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(alternation, "solve_w", recording("w_step", alternation.solve_w))
    monkeypatch.setattr(alternation, "solve_x", recording("x_step", alternation.solve_x))
    monkeypatch.setattr(AndersonMixer, "mix", recording("mix", AndersonMixer.mix))
    problem, _ = synthetic_problem(frames=100, points=5)
    with threadpool_limits(2, user_api="blas"):
        before = _blas_threads()
        alternation.solve(problem)
        assert _blas_threads() == before
    assert seen["w_step"] == seen["x_step"] == {1}
    assert seen["mix"] == set(before)
