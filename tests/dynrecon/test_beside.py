"""dynrecon.beside: a function run beside the caller, in a forked child where safe, gives the function's result,
raises its exception, survives the child's death and never leaves a child behind."""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dynrecon import beside as beside_module
from dynrecon.beside import beside, fork_is_safe, map_beside
from dynrecon.errors import InputError
from dynrecon.warnings_seen import warnings_seen

PARENT = os.getpid()
ROOT = Path(__file__).resolve().parents[2]
INNER = "DYNRECON_FORK_TESTS_INNER"  # set in the fresh interpreter of `test_the_fork_tests_run_somewhere`
# The tests that need a fork: in a long test session other tests (Dask's) leave threads alive, so these may skip there
# and run again in a fresh interpreter
FORK_TESTS = [
    "tests/dynrecon/test_beside.py",
    "tests/reconstruct/test_tracks_referee.py::test_the_referee_in_a_process_gives_what_it_gives_in_a_thread",
    "tests/reconstruct/test_tracks_referee.py::test_a_windowed_referee_starts_after_the_track_search",
]


def where_and_sum(values: np.ndarray) -> tuple[int, float]:
    return os.getpid(), float(values.sum())


def fails() -> None:
    raise ValueError("the function's own error")


def dies_in_a_child(values: np.ndarray) -> float:
    if os.getpid() != PARENT:
        os._exit(3)  # killed, out of memory: no result
    return float(values.sum())


class UnpicklableError(Exception):
    def __reduce__(self) -> str:  # type: ignore[override]
        raise TypeError("not picklable")


def raises_unpicklable() -> None:
    raise UnpicklableError("kept")


def raises_input_error() -> None:
    raise InputError("tracks.csv", "no rows", where="line 2", fix="track something first")


def cleans_up_when_stopped(marker: str) -> None:
    try:  # the file is made inside the try: a stop that comes as soon as it exists still finds the cleanup armed
        with open(marker, "w") as file:
            file.write("working")
        time.sleep(60)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(marker)  # a temporary file of the function's own


@pytest.fixture
def single_threaded() -> None:
    if not fork_is_safe():
        pytest.skip(f"fork is not used here: threads {threading.enumerate()} alive, or not Linux")


def test_a_forked_child_returns_the_result(single_threaded: None) -> None:
    values = np.arange(1000.0)
    with beside(where_and_sum, values) as running:
        assert running.forked
        pid, total = running.result()
    assert pid != os.getpid()
    assert total == values.sum()


def test_the_child_s_exception_is_raised_in_the_caller(single_threaded: None) -> None:
    with beside(fails) as running, pytest.raises(ValueError, match="the function's own error"):
        running.result()


def test_a_child_that_dies_without_a_result_is_redone_here(single_threaded: None) -> None:
    values = np.arange(10.0)
    with beside(dies_in_a_child, values) as running:
        assert running.result() == values.sum()
        assert running.redone


def stuck_in_a_child(values: np.ndarray) -> float:
    if os.getpid() != PARENT:
        held = threading.Lock()  # as a lock that a thread gone with the fork held: no CPU time, no end
        held.acquire()
        held.acquire(timeout=60)
    return float(values.sum())


def test_a_stuck_child_is_stopped_and_its_work_redone_here(
    single_threaded: None, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(beside_module, "STALL_S", 1.0)
    monkeypatch.setattr(beside_module, "_WATCH_S", 0.1)
    values = np.arange(4.0)
    started = time.perf_counter()
    with beside(stuck_in_a_child, values) as running:
        pid = running._pid
        assert running.result() == values.sum() and running.redone
    assert time.perf_counter() - started < 20  # not the child's 60 s
    assert "used no CPU time for 1 s (stuck)" in caplog.text
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)  # stopped and reaped


def test_without_proc_a_long_child_is_never_taken_for_stuck(
    single_threaded: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(beside_module, "STALL_S", 0.3)
    monkeypatch.setattr(beside_module, "_WATCH_S", 0.05)
    monkeypatch.setattr(beside_module, "_cpu_ticks", lambda pid: None)  # no /proc to read
    with beside(where_and_sum_slowly, np.arange(3.0)) as running:
        pid, total = running.result()
    assert running.forked and not running.redone and pid != os.getpid() and total == 3.0


def where_and_sum_slowly(values: np.ndarray) -> tuple[int, float]:
    time.sleep(1.0)
    return os.getpid(), float(values.sum())


def hides_a_progress_lock(values: np.ndarray) -> float:
    from tqdm import tqdm

    tqdm.get_lock().acquire()  # a bar's lock, never released: the child ends holding it
    return float(values.sum())


def test_a_child_ending_inside_a_progress_bar_leaves_the_caller_s_bars_free(single_threaded: None) -> None:
    from tqdm import tqdm

    for _ in tqdm(range(2), disable=False):  # the caller's lock exists before the fork, as after any bar
        pass
    with beside(hides_a_progress_lock, np.arange(3.0)) as running:
        assert running.result() == 3.0 and running.forked
    lock = tqdm.get_lock()
    assert all(inner.acquire(timeout=5) for inner in lock.locks)  # with tqdm's shared lock: stuck forever
    lock.release()


def test_an_unpicklable_exception_is_raised_by_the_rerun(single_threaded: None) -> None:
    with beside(raises_unpicklable) as running, pytest.raises(UnpicklableError, match="kept"):
        running.result()


def test_a_user_error_comes_back_whole(single_threaded: None) -> None:
    with beside(raises_input_error) as running, pytest.raises(InputError) as raised:
        running.result()
    assert str(raised.value) == "tracks.csv:line 2: no rows (track something first)"
    assert raised.value.fix == "track something first" and not running.redone  # not run a second time


def test_a_child_stopped_early_runs_its_cleanup(single_threaded: None, tmp_path) -> None:
    marker = tmp_path / "working.txt"
    with beside(cleans_up_when_stopped, str(marker)) as running:
        assert running.forked
        for _ in range(500):  # until the child has started its work
            if marker.exists():
                break
            time.sleep(0.01)
        assert marker.exists()
    assert not marker.exists()  # SIGTERM became SystemExit in the child: its finally ran


def warns(text: str) -> int:
    logging.getLogger("dynrecon.test").warning("a warning from %s", text)
    return os.getpid()


def test_a_child_s_warnings_reach_the_caller_s_collector(single_threaded: None) -> None:
    with warnings_seen() as seen:
        logging.getLogger("dynrecon.test").warning("the caller's own")
        with beside(warns, "the child") as running:
            pid = running.result()
    assert running.forked and pid != os.getpid()
    assert seen.messages == ["the caller's own", "a warning from the child"]


def test_when_fork_fails_a_thread_does_the_work(single_threaded: None, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_fork() -> int:
        raise BlockingIOError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(os, "fork", no_fork)
    values = np.arange(7.0)
    with beside(where_and_sum, values) as running:
        assert not running.forked
        assert running.result() == (os.getpid(), values.sum())


def test_closing_early_stops_and_reaps_the_child(single_threaded: None) -> None:
    started = time.perf_counter()
    with beside(time.sleep, 60) as running:
        pid = running._pid
    assert time.perf_counter() - started < 10
    assert pid is not None
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)  # reaped already: no zombie left


def test_without_fork_it_runs_in_a_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(beside_module.NO_FORK, "1")
    values = np.arange(5.0)
    with beside(where_and_sum, values) as running:
        assert not running.forked
        assert running.result() == (os.getpid(), values.sum())
    with beside(fails) as running, pytest.raises(ValueError):
        running.result()


def where_and_square(value: int) -> tuple[int, int]:
    return os.getpid(), value * value


def test_a_map_beside_gives_the_list_in_order_half_of_it_from_a_child(single_threaded: None) -> None:
    out = map_beside(where_and_square, list(range(7)), "squares")
    assert [square for _, square in out] == [k * k for k in range(7)]
    assert {pid for pid, _ in out[::2]} == {os.getpid()}
    assert {pid for pid, _ in out[1::2]} != {os.getpid()} and len({pid for pid, _ in out[1::2]}) == 1
    assert map_beside(where_and_square, [3]) == [(os.getpid(), 9)] and map_beside(where_and_square, []) == []


def test_a_map_beside_without_fork_gives_the_same_list(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(beside_module.NO_FORK, "1")
    assert map_beside(where_and_square, list(range(5))) == [(os.getpid(), k * k) for k in range(5)]
    with pytest.raises(ValueError, match="the function's own error"):
        map_beside(lambda _: fails(), [1, 2])


def test_the_fork_tests_run_somewhere() -> None:
    # always: the test workers take whole modules, so a fork test of another module may have skipped elsewhere
    if os.environ.get(INNER):
        pytest.skip("this is the fresh interpreter the fork tests run in")
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", "-rs", *FORK_TESTS],
        cwd=ROOT,
        env={**os.environ, INNER: "1"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "fork is not used here" not in result.stdout, result.stdout[-4000:]


def test_within_one_core_the_work_runs_in_the_caller_when_asked_for() -> None:
    """`register --threads 1` (a user sharing the machine): nothing beside, neither a child nor a thread; the
    function runs in the caller at `result()`, its exception raised there; outside the block, beside again."""
    from dynrecon.beside import one_core

    ran: list[int] = []
    with one_core(), beside(lambda: ran.append(threading.get_ident()) or os.getpid()) as running:
        assert ran == []  # not started: nothing runs beside the caller
        assert running.result() == os.getpid() and ran == [threading.get_ident()] and not running.forked
    with one_core(), pytest.raises(ZeroDivisionError), beside(lambda: 1 / 0) as failing:
        failing.result()
    assert map_beside(abs, [-1, 2, -3]) == [1, 2, 3]


def test_within_one_core_the_work_runs_once() -> None:
    from dynrecon.beside import one_core

    calls: list[int] = []
    with one_core(), beside(lambda: calls.append(1) or len(calls)) as running:
        assert (running.result(), running.result(), calls, running.inline) == (1, 1, [1], True)
