"""Lock files that keep a second process off a folder it would write into at the same time.

`WS/.labeling.lock` (`WorkspaceLock`) keeps a second labeling server off a workspace; `OUT/.dynrecon.lock`
(`OutputLock`) keeps a second `run`, `register`, `solve`, `batch` or `export` off an output folder, whose files two
writers would mix (each told it succeeded), and a writer of a stage folder off a `run`'s workspace (marked by its
pipeline.json, or by its lock's `"workspace": true`). A lock holds its owner's pid (and the server's URL); one
whose pid no longer runs (a crashed or killed process) is taken over.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import time
from pathlib import Path

from dynrecon.atomic import require_writable
from dynrecon.errors import DynreconError

log = logging.getLogger(__name__)

LOCK_NAME = ".labeling.lock"
OUTPUT_LOCK_NAME = ".dynrecon.lock"
NEARBY_LEVELS = 2  # folders above an output folder whose writers are refused beside it (WS of WS/register/...)
WORKSPACE_MARK = "pipeline.json"  # dynrecon.pipeline_state.STATE_NAME (the ground imports no other module)
STAGE_FOLDERS = ("register", "register_subject")  # a workspace's folders that `register` may also be given


class WorkspaceLockedError(DynreconError):
    """Another live process holds this folder."""


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


class WorkspaceLock:
    """Create with `acquire()`; `release()` removes the file only if it is still ours. `holder` and `advice` word
    the refusal of a second process."""

    holder = "labeling server"
    advice = "use that one, or stop it; delete the lock file only if no server is running"

    def __init__(self, workspace: Path, name: str = LOCK_NAME):
        self.path = workspace / name
        self.token = f"{os.getpid()}-{id(self)}"
        self.held = False
        self.marks: dict[str, object] = {}  # more of the owner's facts for other processes to read

    def __enter__(self) -> WorkspaceLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def acquire(self, url: str = "") -> None:
        body = json.dumps(
            {"pid": os.getpid(), "host": socket.gethostname(), "url": url, "token": self.token, **self.marks}
        )
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                owner = self._read_owner()
                if owner is None and self._age() < 2.0:  # being written right now: read again once it settles
                    time.sleep(0.2)
                    owner = self._read_owner()
                if self._stale(owner):
                    log.warning("taking over the stale lock %s (%s)", self.path, owner)
                    self.path.unlink(missing_ok=True)
                    continue
                where = f" at {owner['url']}" if owner and owner.get("url") else ""
                pid = owner.get("pid") if owner else "?"
                raise WorkspaceLockedError(  # noqa: B904 (not raised from an exception)
                    f"{self.path}: another {self.holder} (pid {pid}){where} is using this folder ({self.advice})"
                )
            with os.fdopen(fd, "w", encoding="utf-8") as handle:
                handle.write(body)
            self.held = True
            return
        raise WorkspaceLockedError(f"{self.path}: could not take the lock (a process keeps recreating it)")

    def update_url(self, url: str) -> None:
        """Record the final URL (known only after binding) for the refusal message of a second server."""
        if self.held:
            self.path.write_text(
                json.dumps(
                    {"pid": os.getpid(), "host": socket.gethostname(), "url": url, "token": self.token, **self.marks}
                ),
                encoding="utf-8",
            )

    def _age(self) -> float:
        try:
            return time.time() - self.path.stat().st_mtime
        except FileNotFoundError:
            return 0.0

    def _stale(self, owner: dict | None) -> bool:
        # Unreadable and not fresh: a server killed mid-write. A pid can only be checked on its own host.
        if owner is None:
            return self._age() >= 2.0
        try:
            pid = int(owner.get("pid", -1))
        except (TypeError, ValueError):
            return True
        return owner.get("host") == socket.gethostname() and not _pid_alive(pid)

    def _read_owner(self) -> dict | None:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def release(self) -> None:
        if self.held:
            owner = self._read_owner()
            if owner is not None and owner.get("token") == self.token:
                self.path.unlink(missing_ok=True)
            self.held = False


class OutputLock(WorkspaceLock):
    """`OUT/.dynrecon.lock`: one writing command per output folder (made when missing). `workspace`: the command
    writes a pipeline workspace (`run`), whose stage folders it owns from its start, before pipeline.json exists."""

    holder = "dynrecon command"
    advice = "wait for it to finish, or give another --out; delete the lock file only if no dynrecon runs"

    def __init__(self, folder: Path, *, workspace: bool = False):
        super().__init__(folder, OUTPUT_LOCK_NAME)
        self.made = False
        self.workspace = workspace
        if workspace:
            self.marks["workspace"] = True

    def acquire(self, url: str = "") -> None:
        folder = self.path.parent
        require_writable(folder)  # one line for a file in the way or a folder without permission
        self.made = not folder.exists()
        folder.mkdir(parents=True, exist_ok=True)
        super().acquire(url)
        # a command writing the workspace above (`run --out WS`) or a stage folder within (`register --out
        # WS/register`) writes the same files: refused too (only a workspace's: pipeline.json marks one, or the lock
        # of a `run` that has not written it yet)
        resolved = folder.resolve()
        nearby = [p / OUTPUT_LOCK_NAME for p in list(resolved.parents)[:NEARBY_LEVELS]]
        if self.workspace or (resolved / WORKSPACE_MARK).is_file():
            nearby += [resolved / stage / OUTPUT_LOCK_NAME for stage in STAGE_FOLDERS]
        for path in nearby:
            other = WorkspaceLock(path.parent, OUTPUT_LOCK_NAME)
            owner = other._read_owner() if path.is_file() else None
            if owner is None and path.is_file() and other._age() < 2.0:  # being written right now: read it settled
                time.sleep(0.2)
                owner = other._read_owner()
            above = path.parent in resolved.parents
            marked = owner is not None and owner.get("workspace") is True
            if above and owner is not None and not (marked or (path.parent / WORKSPACE_MARK).is_file()):
                continue  # a folder above that is no workspace: an unrelated writer (`export --out .`)
            if owner is not None and not other._stale(owner):
                self.release()
                raise WorkspaceLockedError(
                    f"{path}: another {self.holder} (pid {owner.get('pid', '?')}) is writing {path.parent}, which "
                    f"{'holds' if above else 'is within'} this folder ({self.advice})"
                )

    def release(self) -> None:
        super().release()
        if self.made:  # a command refused before writing anything leaves no empty folder behind
            with contextlib.suppress(OSError):
                self.path.parent.rmdir()
