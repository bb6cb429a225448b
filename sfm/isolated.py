"""Run a pycolmap stage in a child Python process, so that a fatal COLMAP error (SIGABRT from a failed CHECK in
a worker thread) becomes a clear DynreconError instead of killing the CLI.

The child (`python -m sfm.isolated CALL RESULT LOG PARENT_PID`) writes glog output (COLMAP's own log) to LOG; its
progress bars go to the parent's stderr; it ends when its parent does. Arguments and results cross as pickles of
plain values.
"""

from __future__ import annotations

import importlib
import logging
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dynrecon.bar_lines import LineStream
from dynrecon.beside import end_with_parent
from dynrecon.errors import DynreconError

log = logging.getLogger(__name__)


class ColmapCrashError(DynreconError):
    """pycolmap died or failed inside a stage; the message names the stage and COLMAP's log file."""


def run_isolated(stage: str, func: Callable[..., Any], kwargs: dict[str, Any], log_path: Path) -> Any:
    """Call `func(**kwargs)` (a module-level function) in a fresh Python process and return its result."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "a", encoding="utf-8") as handle:
        handle.write(f"\n===== dynrecon stage: {stage} =====\n")
    with tempfile.TemporaryDirectory(prefix="dynrecon-colmap-") as tmp:
        call, result = Path(tmp) / "call.pkl", Path(tmp) / "result.pkl"
        call.write_bytes(pickle.dumps((func.__module__, func.__qualname__, kwargs)))
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
        process = subprocess.run(
            [sys.executable, "-m", "sfm.isolated", str(call), str(result), str(log_path), str(os.getpid())],
            env=env,
            check=False,
        )
        code = process.returncode
        if code != 0 or not result.exists():
            how = f"was killed by signal {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}"
            raise ColmapCrashError(f"pycolmap {stage} {how}; the end of COLMAP's log {log_path} says why")
        status, value = pickle.loads(result.read_bytes())
    if status != "ok":
        log.debug("%s failed in the child process:\n%s", stage, value)
        raise ColmapCrashError(f"pycolmap {stage} failed: {value.splitlines()[0]} (log: {log_path})")
    return value


def _child(call: Path, result: Path, log_path: Path, parent: int) -> None:
    # A parent killed outright (SIGKILL, or a Dask nanny ending its worker) would leave this stage running,
    # writing into the workspace after the command has ended.
    end_with_parent(signal.SIGKILL)
    if os.getppid() != parent:  # the parent ended before the line above
        sys.exit(1)
    progress = os.dup(2)
    with open(log_path, "a", encoding="utf-8") as handle:
        os.dup2(handle.fileno(), 2)  # glog (COLMAP's log) writes to fd 2
    stream = os.fdopen(progress, "w", buffering=1)  # tqdm writes to sys.stderr: the user's terminal, or log file
    sys.stderr = stream if stream.isatty() else LineStream(stream)
    import pycolmap

    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a stop, not a crash: no native stack trace in the log
    pycolmap.logging.logtostderr = True
    pycolmap.logging.minloglevel = 0
    module, name, kwargs = pickle.loads(call.read_bytes())
    try:
        value: tuple[str, Any] = ("ok", getattr(importlib.import_module(module), name)(**kwargs))
    except Exception as error:  # reported by the parent as a one-line error; the traceback goes to the log
        traceback.print_exc(file=open(log_path, "a", encoding="utf-8"))  # noqa: SIM115
        value = ("error", f"{type(error).__name__}: {error}")
    result.write_bytes(pickle.dumps(value))


if __name__ == "__main__":
    try:
        _child(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]))
    except KeyboardInterrupt:  # Ctrl+C reaches the whole process group: the parent says "interrupted", once
        sys.exit(130)
