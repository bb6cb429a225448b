"""Run a function beside the caller's own work: in a forked child process where that is safe, else in a thread.

Two pieces of pure-Python-heavy numpy work in threads of one process take turns on the GIL and run about one after
the other. A forked child runs on the other core; it shares the caller's memory copy-on-write, so nothing but the
result crosses (pickled, through a pipe). Fork is used only on Linux, from the main thread, and only while no other
Python thread runs: a lock held by another thread at the fork (tqdm's monitor takes tqdm's lock every few seconds,
a Dask worker's event loop holds its own) stays held in the child forever. The command line switches tqdm's
monitor off (`quiet_tqdm_monitor`) so that it never starts. Everywhere else, when fork fails, and with
DYNRECON_NO_FORK set, the function runs in a thread. Within `one_core()` (`register --threads 1`: a user sharing
the machine) nothing runs beside: the function runs in the caller when its result is asked for.

The result is the function's, whichever way it ran: a child that dies without one (killed, out of memory), whose
result cannot be brought back, or that uses no CPU time for STALL_S (stuck on a lock a native thread held at the
fork), is not trusted for anything, and the function is run again in the caller (`redone`). The child's progress
bars take a lock of its own: tqdm's default lock is shared across fork, and a child ending while it held it would
stop every later bar of the caller. A child stopped early (the caller failed first) gets SIGTERM, which its function
sees as SystemExit, so that its own cleanup (temporary files) runs; SIGKILL follows if it does not end. The warnings
a child logs reach the caller's `warnings_seen` collectors with its result.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import pickle
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Generic, TypeVar

from dynrecon.warnings_seen import WarningsSeen

log = logging.getLogger(__name__)

T = TypeVar("T")
A = TypeVar("A")
NO_FORK = "DYNRECON_NO_FORK"  # set to anything: always a thread
STOP_GRACE_S = 5.0  # a child stopped early has this long to clean up after SIGTERM (a loaded machine delays it)
# A child that used no CPU time for this long is stuck (computing children never wait this long; a child's own
# children's time is not counted: nothing run beside waits on one)
STALL_S = 120.0
_WATCH_S = 5.0  # how often the caller, waiting for the result, looks at the child's CPU time
_PR_SET_PDEATHSIG = 1


_one_core = threading.local()  # per thread: how many `one_core` blocks are open


@contextlib.contextmanager
def one_core() -> Iterator[None]:
    """Within the block, `beside` runs nothing beside the caller: each function runs in the caller when its
    result is asked for (one core, as `--threads 1` asks)."""
    _one_core.depth = getattr(_one_core, "depth", 0) + 1
    try:
        yield
    finally:
        _one_core.depth -= 1


def fork_is_safe() -> bool:
    """Whether `beside` may fork here: Linux, fork available, the main thread, no other Python thread alive, not
    switched off. (Native threads, e.g. BLAS pools, are not seen: their libraries handle fork.)"""
    return (
        sys.platform == "linux"
        and hasattr(os, "fork")
        and not os.environ.get(NO_FORK)
        and threading.current_thread() is threading.main_thread()
        and threading.active_count() == 1
    )


def end_with_parent(signum: int) -> None:
    """Have Linux send `signum` to this process when the thread that started it ends (elsewhere: nothing), so that a
    child never runs on, orphaned, after its caller was killed."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signum)


def quiet_tqdm_monitor() -> None:
    """Keep tqdm from starting its monitor thread (it only adjusts refresh intervals), so that `beside` can fork."""
    with contextlib.suppress(ImportError):
        from tqdm import tqdm

        tqdm.monitor_interval = 0


class Beside(Generic[T]):
    """The handle of a call started by `beside`: `result()` waits for it and returns its value or raises its
    exception. Use it as a context manager, so that a child is never left behind when the caller fails.
    `forked`: it ran in a child process; `inline`: within `one_core`, in the caller at `result()`; `redone`: the
    child gave no result and the caller ran it again."""

    def __init__(self, function: Callable[..., T], args: tuple[Any, ...]) -> None:
        self._function, self._args = function, args
        self._pid: int | None = None
        self._read: int | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._future: Future[T] | None = None
        self.redone = False
        self._inline = self.inline = getattr(_one_core, "depth", 0) > 0
        self.forked = not self._inline and fork_is_safe() and self._start_child()
        if not self.forked and not self._inline:
            self._pool = ThreadPoolExecutor(1)
            self._future = self._pool.submit(function, *args)

    def _start_child(self) -> bool:
        for stream in (sys.stdout, sys.stderr):  # else the child would write the caller's pending output again
            with contextlib.suppress(Exception):
                stream.flush()
        read, write = os.pipe()
        try:
            pid = os.fork()
        except OSError as error:  # no process to be had (a process limit, memory): a thread does the same work
            os.close(read)
            os.close(write)
            log.info("no worker process (%s): a thread runs the work instead", error)
            return False
        if pid == 0:  # the child: never returns into the caller's code
            os.close(read)
            _child(write, self._function, self._args)
        self._pid = pid
        os.close(write)
        self._read = read
        return True

    def result(self) -> T:
        """The function's return value (waits); its exception is raised here."""
        if self._inline:  # run once, at the first call, as the other ways run once
            if self._future is None:
                self._future = Future()
                try:
                    self._future.set_result(self._function(*self._args))
                except BaseException as error:
                    self._future.set_exception(error)
            return self._future.result()
        if self._future is not None:
            return self._future.result()
        payload = self._collect()
        if payload is None:
            log.warning("a worker process ended without a usable result; running its work here instead")
            self.redone = True
            return self._function(*self._args)
        failed, value, warned = payload
        for handler in _collectors():
            for message in warned:
                handler.add(message)
        if failed:
            raise value
        return value

    def _collect(self) -> tuple[bool, Any, list[str]] | None:
        """The child's (failed, value, warnings it logged), or None when it gave none. Reaps it."""
        assert self._read is not None
        chunks = []
        with os.fdopen(self._read, "rb", buffering=0) as pipe:
            self._read = None
            busy, still_since = _cpu_ticks(self._pid), time.monotonic()
            ready = select.poll()  # not select(): it refuses descriptors above 1023
            ready.register(pipe.fileno(), select.POLLIN)
            while True:
                if ready.poll(_WATCH_S * 1000):  # data, or the end (POLLHUP)
                    if not (chunk := pipe.read(1 << 20)):
                        break
                    chunks.append(chunk)
                    continue
                ticks = _cpu_ticks(self._pid)
                if ticks is None or ticks != busy:  # unknown (no /proc) is never taken for stuck
                    busy, still_since = ticks, time.monotonic()
                elif time.monotonic() - still_since > STALL_S:
                    log.warning("a worker process used no CPU time for %.0f s (stuck): it is stopped", STALL_S)
                    self.close()
                    return None
        exit_code = self._reap()
        if not chunks or exit_code not in (0, None):
            return None
        try:
            payload = pickle.loads(b"".join(chunks))
        except Exception:  # a truncated or unreadable result is no result
            return None
        return payload

    def _reap(self, timeout: float | None = None) -> int | None:
        """Wait for the child (at most `timeout` s, polling); its exit code, None when someone else reaped it or
        it is still running after the timeout."""
        pid, self._pid = self._pid, None
        if pid is None:
            return None
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                done, status = os.waitpid(pid, 0 if deadline is None else os.WNOHANG)
                if done:
                    return os.waitstatus_to_exitcode(status)
                if deadline is not None and time.monotonic() > deadline:
                    self._pid = pid
                    return None
                time.sleep(0.01)
        except ChildProcessError:  # reaped elsewhere (an embedding application ignoring SIGCHLD)
            return None

    def close(self) -> None:
        """Stop and reap a child still running (the caller failed first): SIGTERM, then SIGKILL after
        STOP_GRACE_S; shut a thread down (it runs to its end: a thread cannot be stopped)."""
        if self._pid is not None:
            for sig, grace in ((signal.SIGTERM, STOP_GRACE_S), (signal.SIGKILL, None)):
                with contextlib.suppress(OSError):
                    os.kill(self._pid, sig)
                self._reap(grace)
                if self._pid is None:
                    break
        if self._read is not None:
            os.close(self._read)
            self._read = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> Beside[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def beside(function: Callable[..., T], *args: Any) -> Beside[T]:
    """Start `function(*args)` beside the caller (a forked child where safe, else a thread); see the module."""
    return Beside(function, args)


def map_beside(function: Callable[[A], T], items: Sequence[A], progress: str | None = None) -> list[T]:
    """`[function(x) for x in items]`, every other item beside the caller (`beside`): the same list, in order,
    where each call depends on its item alone. `progress`: a tqdm bar's label, over the caller's share."""
    from tqdm import tqdm

    def bar() -> Iterable[A]:  # made after the fork: tqdm's monitor thread, where it starts one, would prevent it
        return tqdm(items[::2], desc=progress, leave=False, disable=progress is None)

    if len(items) < 2:
        return [function(x) for x in bar()]
    with beside(_mapped, function, items[1::2]) as running:
        mine = _mapped(function, bar())
        theirs = running.result()
    return [mine[k // 2] if k % 2 == 0 else theirs[k // 2] for k in range(len(items))]


def _mapped(function: Callable[[A], T], items: Iterable[A]) -> list[T]:
    return [function(x) for x in items]


def _child(write: int, function: Callable[..., Any], args: tuple[Any, ...]) -> None:
    """Run the function, send (failed, value, the warnings it logged) through `write`, and leave without running the
    caller's exit code."""
    code = 1
    try:
        # SIGTERM (the caller stopping it) becomes SystemExit, so that the function's cleanup runs; and the child
        # ends with the caller, whatever ended that
        signal.signal(signal.SIGTERM, _exit_on_signal)
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        end_with_parent(signal.SIGTERM)
        _private_progress_lock()
        # the warnings it logs go back to the caller's collectors (`dynrecon run` repeats them at its end)
        collectors = _collectors()
        before = [len(h.messages) for h in collectors]
        try:
            outcome: tuple[bool, Any] = (False, function(*args))
        except BaseException as error:  # the caller re-raises it
            outcome = (True, error)
        warned = list(dict.fromkeys(m for h, n in zip(collectors, before, strict=True) for m in h.messages[n:]))
        data = pickle.dumps((*outcome, warned), protocol=pickle.HIGHEST_PROTOCOL)
        pickle.loads(data)  # what cannot be brought back is sent as nothing: the caller runs the function itself
        with os.fdopen(write, "wb") as pipe:
            pipe.write(data)
        code = 0
    except BaseException:  # nothing may escape into a copy of the caller
        code = 1
    finally:
        os._exit(code)


def _private_progress_lock() -> None:
    """Give this child's tqdm bars a lock of their own, and no monitor thread (see the module)."""
    with contextlib.suppress(ImportError):
        from tqdm import tqdm

        tqdm.monitor_interval = 0
        tqdm.set_lock(threading.RLock())


def _cpu_ticks(pid: int | None) -> int | None:
    """The CPU time (clock ticks, all its threads) process `pid` has used; None where Linux's /proc does not tell."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime, stime
    except (OSError, IndexError, ValueError):
        return None


def _collectors() -> list[WarningsSeen]:
    return [h for h in logging.getLogger().handlers if isinstance(h, WarningsSeen)]


def _exit_on_signal(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


__all__ = ["STALL_S", "Beside", "beside", "fork_is_safe", "map_beside", "one_core"]
