"""The workspace lock file: refuse a live owner, take over a dead one, release only our own."""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

import pytest

from dynrecon.lock import LOCK_NAME, WorkspaceLock, WorkspaceLockedError


def test_live_owner_refuses_and_release_removes(tmp_path: Path) -> None:
    first = WorkspaceLock(tmp_path)
    first.acquire("http://127.0.0.1:1234/")
    with pytest.raises(WorkspaceLockedError, match=r"pid \d+\) at http://127.0.0.1:1234/"):
        WorkspaceLock(tmp_path).acquire()
    first.release()
    assert not (tmp_path / LOCK_NAME).exists()
    second = WorkspaceLock(tmp_path)
    second.acquire()
    second.release()


def test_unreadable_lock_is_refused_while_fresh_and_taken_over_when_old(tmp_path: Path) -> None:
    path = tmp_path / LOCK_NAME
    path.write_text("{garbage")
    with pytest.raises(WorkspaceLockedError):
        WorkspaceLock(tmp_path).acquire()
    old = time.time() - 60
    os.utime(path, (old, old))
    lock = WorkspaceLock(tmp_path)
    lock.acquire()
    assert json.loads(path.read_text())["pid"] == os.getpid()
    lock.release()


def test_lock_of_another_host_is_not_judged_by_pid(tmp_path: Path) -> None:
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": 999999999, "host": socket.gethostname() + "-other"}))
    with pytest.raises(WorkspaceLockedError):
        WorkspaceLock(tmp_path).acquire()


def test_release_leaves_a_lock_taken_over_by_someone_else(tmp_path: Path) -> None:
    lock = WorkspaceLock(tmp_path)
    lock.acquire()
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": os.getpid(), "host": "x", "token": "other"}))
    lock.release()
    assert (tmp_path / LOCK_NAME).exists()
