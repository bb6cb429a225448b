"""The labeling page's live `labels.csv` (format: `tracking.labels`): a store that applies the page's changes."""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from dynrecon.atomic import publish, remove_temp_files
from dynrecon.errors import InputError
from tracking.labels import Key, Label, read_labels, write_labels

# How long a re-read waits for an outside writer that is half-way through labels.csv (empty or cut mid-row).
SETTLE_SECONDS = 0.3
MERGE_ATTEMPTS = 5  # merges before a write goes ahead even though labels.csv keeps changing


@dataclass(frozen=True, kw_only=True)
class Change:
    """Set (video, frame, point) to `label`, or remove its label when `label` is None."""

    key: Key
    label: Label | None


# Changes (labels, page labels) in place; False when there is nothing to write.
Edit = Callable[[dict[Key, Label], dict[Key, Label]], bool]


class SaveError(Exception):
    """labels.csv (or another workspace file) could not be written: a full disk, a read-only folder, no permission.

    `disk_full` tells the server to answer 507 (Insufficient Storage) rather than 503; the message is one line
    that names the file and the system's reason, shown as is by the page.
    """

    def __init__(self, path: Path, error: OSError):
        self.path = path
        self.disk_full = error.errno in (errno.ENOSPC, errno.EDQUOT)
        reason = error.strerror or str(error)
        if self.disk_full:
            fix = "free some disk space; the page keeps the change and retries"
        elif error.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
            fix = "make the workspace folder writable; the page keeps the change and retries"
        else:
            fix = "the page keeps the change and retries"
        super().__init__(f"cannot save {path.name}: {reason} ({fix})")


class StoreClosedError(Exception):
    """A change that arrived while the server stops: it is refused, not half-written."""


class LabelStore:
    """`labels.csv` behind a lock: each change batch is applied and written before the call returns.

    Before every write the file is re-read and merged under the lock, so edits made outside the server (another
    tool, a text editor) are kept. The merge never drops a label the page set: an outside writer that rewrites
    the file from an older copy (or is caught half-way) loses no click. Outside values win for the keys they
    contain (the later writer), and outside deletions of keys the page never set are kept.
    """

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()
        self._labels: dict[Key, Label] = {}
        self._page: dict[Key, Label] = {}  # what the page set in this session: never dropped by a merge
        self._signature: tuple[int, int, int] | None = None
        self._known: bytes | None = None  # labels.csv's bytes as last written or merged: no need to parse again
        self._closed = False
        # Temporary files of a server killed mid-write; the workspace lock keeps other servers off this file.
        remove_temp_files(path)
        remove_temp_files(path.with_name(f".{path.name}"))  # those of the staged copies (see _write)
        with self._lock:
            self._merge_disk()

    def _stat_signature(self) -> tuple[int, int, int] | None:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return None
        return st.st_mtime_ns, st.st_size, st.st_ino

    def _read_bytes(self) -> bytes | None:
        try:
            return self.path.read_bytes()
        except OSError:  # missing, or unreadable: read_labels says which
            return None

    def _read_settled(self) -> tuple[dict[Key, Label], tuple[int, int, int] | None, bytes | None]:
        """Read labels.csv, again while an outside writer is visibly mid-write (file changing, empty, cut)."""
        deadline = time.monotonic() + SETTLE_SECONDS
        while True:
            before = self._stat_signature()
            raw = self._read_bytes()
            try:
                labels = read_labels(self.path)
                error: InputError | None = None
            except InputError as caught:
                labels, error = {}, caught
            after = self._stat_signature()
            truncated = after is not None and after[1] == 0 and bool(self._labels)
            if before == after and error is None and not truncated:
                return labels, after, raw
            if time.monotonic() >= deadline:
                if error is not None:
                    raise error
                return labels, after, None
            time.sleep(0.02)

    def _merge_disk(self) -> None:
        """Re-read labels.csv (a stat can miss an edit on a coarse clock) and merge it with the page's labels."""
        signature = self._stat_signature()
        # Same bytes as last time: the memory already holds them merged (parsing is the slow part of a click).
        if self._known is not None and signature is not None and self._read_bytes() == self._known:
            self._signature = signature
            return
        disk, signature, self._known = self._read_settled()
        for key, label in self._page.items():
            disk.setdefault(key, label)  # a click the outside writer did not know about
        self._labels = disk
        self._signature = signature

    def snapshot(self, video: str | None = None) -> dict[Key, Label]:
        with self._lock:
            self._merge_disk()
            return {k: v for k, v in self._labels.items() if video is None or k[0] == video}

    def _write(self, labels: dict[Key, Label], point_order: list[str] | None, *, check: bool) -> bool:
        """Write `labels`; with `check`, not if labels.csv changed since it was merged (False: merge again).

        The file is staged beside labels.csv and renamed over it only after that check, which narrows the
        window in which an outside edit could be overwritten from the time of a whole write to that of a stat.
        """
        if self._closed:
            raise StoreClosedError("the labeling server is stopping; the change was not saved")
        staged = self.path.with_name(f".{self.path.name}.{os.getpid()}-{threading.get_ident()}.tmp")
        try:
            write_labels(staged, labels, point_order)
            if check and self._stat_signature() != self._signature:
                staged.unlink()
                return False
            written = staged.read_bytes()
            publish(staged, self.path)
        except BaseException as error:
            with contextlib.suppress(OSError):
                staged.unlink(missing_ok=True)
            if isinstance(error, OSError):
                raise SaveError(self.path, error) from None
            raise
        self._known = written
        return True

    def _merge_and_write(self, edit: Edit, point_order: list[str] | None) -> None:
        """Merge the file, apply `edit` to copies of (labels, page labels), write; again if the file moved meanwhile."""
        for attempt in range(MERGE_ATTEMPTS):
            self._merge_disk()
            labels, page = dict(self._labels), dict(self._page)
            if not edit(labels, page):
                break
            # The last attempt writes whatever happens: a file that never stops changing must not block a click.
            if self._write(labels, point_order, check=attempt < MERGE_ATTEMPTS - 1):
                self._signature = self._stat_signature()
                break
        self._labels, self._page = labels, page

    def apply(self, changes: Iterable[Change], point_order: list[str] | None = None) -> int:
        """Apply a batch atomically (all or nothing on disk); returns the number of labels afterwards."""
        batch = list(changes)

        def edit(labels: dict[Key, Label], page: dict[Key, Label]) -> bool:
            for change in batch:
                if change.label is None:
                    labels.pop(change.key, None)
                    page.pop(change.key, None)
                else:
                    labels[change.key] = change.label
                    page[change.key] = change.label
            return True

        with self._lock:
            self._merge_and_write(edit, point_order)
            return len(self._labels)

    def rename_point(self, old: str, new: str, point_order: list[str] | None = None) -> int:
        """Rename a point in every video; returns the number of rows changed. Never merges two points."""
        changed = 0

        def edit(labels: dict[Key, Label], page: dict[Key, Label]) -> bool:
            nonlocal changed
            if any(k[2] == new for k in labels):
                raise ValueError(f"point {new!r} already has labels")
            changed = sum(1 for k in labels if k[2] == old)
            for table in (labels, page):
                renamed = {(v, f, new if p == old else p): lab for (v, f, p), lab in table.items()}
                table.clear()
                table.update(renamed)
            return changed > 0

        with self._lock:
            self._merge_and_write(edit, point_order)
            return changed

    def close(self) -> None:
        """Wait for a write in progress (a stopping server must not leave a temporary file), refuse later ones."""
        with self._lock:
            self._closed = True
