"""Run a function beside the caller's own work: in a forked child process where that is safe, else in a thread.

Two pieces of pure-Python-heavy numpy work in threads of one process take turns on the GIL and run about one after
the other. A forked child runs on the other core; it shares the caller's memory copy-on-write, so nothing but the
result crosses (pickled, through a pipe). Fork is used only on Linux, from the main thread, and only while no other
thread runs but harmless ones (`HARMLESS_THREADS`): forking a process whose other threads may hold a lock (a Dask
worker's event loop, a library's pool) can deadlock the child. Everywhere else, and with DYNRECON_NO_FORK set, the
function runs in a thread.

The result is the function's, whichever way it ran: a child that dies without one (killed, out of memory) is not
trusted for anything, and the function is run again in the caller.
"""

from __future__ import annotations

import logging
import os
import pickle
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")
NO_FORK = "DYNRECON_NO_FORK"  # set to anything: always a thread


# Threads that hold no lock a child could need: tqdm's monitor only sleeps on its own event between checks of its bars
HARMLESS_THREADS = frozenset({"tqdm_monitor"})


def fork_is_safe() -> bool:
    """Whether `beside` may fork here: Linux, fork available, no other thread alive but harmless ones, not switched
    off."""
    others = [t for t in threading.enumerate() if t is not threading.current_thread()]
    return (
        sys.platform == "linux"
        and hasattr(os, "fork")
        and not os.environ.get(NO_FORK)
        and threading.current_thread() is threading.main_thread()
        and all(t.name in HARMLESS_THREADS and t.daemon for t in others)
    )


class Beside(Generic[T]):
    """The handle of a call started by `beside`: `result()` waits for it and returns its value or raises its
    exception. Use it as a context manager, so that a child is never left behind when the caller fails."""

    def __init__(self, function: Callable[..., T], args: tuple[Any, ...]) -> None:
        self._function, self._args = function, args
        self._pid: int | None = None
        self._read: int | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._future: Future[T] | None = None
        self.forked = fork_is_safe()
        if self.forked:
            self._start_child()
        else:
            self._pool = ThreadPoolExecutor(1)
            self._future = self._pool.submit(function, *args)

    def _start_child(self) -> None:
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the caller's code
            os.close(read)
            _child(write, self._function, self._args)
        os.close(write)
        self._pid, self._read = pid, read

    def result(self) -> T:
        """The function's return value (waits); its exception is raised here."""
        if self._future is not None:
            return self._future.result()
        payload = self._collect()
        if payload is None:
            log.warning("a worker process ended without a result; running its work here instead")
            return self._function(*self._args)
        failed, value = payload
        if failed:
            raise value
        return value

    def _collect(self) -> tuple[bool, Any] | None:
        """The child's (failed, value), or None when it died without one. Reaps it."""
        assert self._read is not None and self._pid is not None
        chunks = []
        with os.fdopen(self._read, "rb") as pipe:
            self._read = None
            while chunk := pipe.read(1 << 20):
                chunks.append(chunk)
        _, status = os.waitpid(self._pid, 0)
        self._pid = None
        if not chunks or os.waitstatus_to_exitcode(status) != 0:
            return None
        try:
            payload = pickle.loads(b"".join(chunks))
        except Exception:  # a truncated or unreadable result is no result
            return None
        return payload

    def close(self) -> None:
        """Stop and reap a child still running (the caller failed first); shut the thread down."""
        if self._pid is not None:
            try:
                os.kill(self._pid, 9)
                os.waitpid(self._pid, 0)
            except OSError:
                pass
            self._pid = None
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


def _child(write: int, function: Callable[..., Any], args: tuple[Any, ...]) -> None:
    """Run the function, send (failed, value) through `write`, and leave without running the caller's exit code."""
    code = 0
    try:
        try:
            payload: tuple[bool, Any] = (False, function(*args))
        except BaseException as error:  # the caller re-raises it
            payload = (True, error)
        # an unpicklable value or exception raises here: no result, and the caller runs the function itself
        data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
        with os.fdopen(write, "wb") as pipe:
            pipe.write(data)
    except BaseException:  # nothing may escape into a copy of the caller
        code = 1
    finally:
        os._exit(code)
