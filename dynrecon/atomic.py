"""Crash-safe file writes: write a temporary file beside the target, fsync, then rename over it."""

from __future__ import annotations

import contextlib
import glob
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from dynrecon.errors import InputError

log = logging.getLogger(__name__)


@contextmanager
def atomic_open(path: str | Path, mode: str = "w", *, newline: str | None = None) -> Iterator[IO]:
    """Open a temporary file that replaces `path` only if the block finishes without an exception.

    A reader never sees a half-written file, and a crash mid-write leaves the old file intact.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder: a file was expected here", fix="give the path of a file")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocking = next((p for p in reversed(path.parents) if p.is_file()), path.parent)
        raise InputError(blocking, "is a file: a folder was expected here", fix="give a path inside a folder") from None
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(tmp_name)
    try:
        binary = "b" in mode
        try:
            handle = os.fdopen(fd, mode, newline=newline, encoding=None if binary else "utf-8")
        except BaseException:
            os.close(fd)  # fdopen did not take the descriptor over
            raise
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        publish(tmp, path)
    except BaseException:
        # Every failure (a full disk at write, flush, fsync or close; a refused rename; an interrupt) leaves no
        # temporary file; a failing unlink must not hide the original error.
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def temp_files(path: str | Path) -> list[Path]:
    """The temporary files `atomic_open(path)` makes beside `path` (left behind only by a killed process)."""
    path = Path(path)
    try:
        return sorted(path.parent.glob(f".{glob.escape(path.name)}.*.tmp"))
    except OSError:
        return []


def remove_temp_files(path: str | Path) -> int:
    """Remove what `temp_files(path)` lists; call it only where no other process writes `path`. Returns the count."""
    removed = 0
    for tmp in temp_files(path):
        with contextlib.suppress(OSError):
            tmp.unlink()
            removed += 1
    return removed


def publish(tmp: Path, path: Path) -> None:
    """Rename a finished temporary file over `path`, with the permissions a plain open() would have given it
    (mkstemp creates 0600 files)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_open(path, "w") as handle:
        handle.write(text)


def require_writable(folder: str | Path) -> Path:
    """Check that files can be written in `folder` (made if missing), before a stage spends its time.

    Folders it had to make are removed again: a stage that then fails on its inputs leaves nothing behind.
    Raises InputError naming the folder and the system's reason (a file in the way, no permission, read-only disk).
    """
    folder = Path(folder)
    made = [p for p in (folder, *folder.parents) if not p.exists()]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=".write-test.", suffix=".tmp", dir=folder)
        os.close(fd)
        os.unlink(tmp_name)
    except FileExistsError:
        raise InputError(
            folder, "cannot write here: it is a file, not a folder", fix="give the path of a folder for the outputs"
        ) from None
    except OSError as error:
        raise InputError(
            folder, f"cannot write here: {error.strerror or error}", fix="give a folder you can write to"
        ) from None
    finally:
        for path in made:  # deepest first
            with contextlib.suppress(OSError):
                path.rmdir()
    return folder


def keep_aside(target: Path, why: str) -> Path:
    """Copy `target` to <stem>.before-<time><suffix> beside it (a copy: it may also be the input the stage about to
    write it reads), with a warning saying `why`; returns that path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    kept = target.with_name(f"{target.stem}.before-{stamp}{target.suffix}")
    n = 1
    while kept.exists():
        n += 1
        kept = target.with_name(f"{target.stem}.before-{stamp}-{n}{target.suffix}")
    shutil.copy2(target, kept)
    log.warning("%s %s: it is kept as %s", target, why, kept.name)
    return kept
