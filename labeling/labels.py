"""The labeling page's live `labels.csv` (format: `tracking.labels`): a store that applies the page's changes."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from tracking.labels import Key, Label, read_labels, write_labels


@dataclass(frozen=True, kw_only=True)
class Change:
    """Set (video, frame, point) to `label`, or remove its label when `label` is None."""

    key: Key
    label: Label | None


class LabelStore:
    """`labels.csv` behind a lock: each change batch is applied and written before the call returns.

    The file is re-read when someone else changed it since our last write (stat signature), so edits made
    outside the server (another tool, a text editor) are merged rather than clobbered.
    """

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()
        self._labels: dict[Key, Label] = {}
        self._signature: tuple[int, int] | None = None
        with self._lock:
            self._reload_if_changed()

    def _stat_signature(self) -> tuple[int, int] | None:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return None
        return st.st_mtime_ns, st.st_size

    def _reload_if_changed(self) -> None:
        signature = self._stat_signature()
        if signature != self._signature or signature is None:
            self._labels = read_labels(self.path)
            self._signature = signature

    def snapshot(self, video: str | None = None) -> dict[Key, Label]:
        with self._lock:
            self._reload_if_changed()
            return {k: v for k, v in self._labels.items() if video is None or k[0] == video}

    def apply(self, changes: Iterable[Change], point_order: list[str] | None = None) -> int:
        """Apply a batch atomically (all or nothing on disk); returns the number of labels afterwards."""
        with self._lock:
            self._reload_if_changed()
            labels = dict(self._labels)
            for change in changes:
                if change.label is None:
                    labels.pop(change.key, None)
                else:
                    labels[change.key] = change.label
            write_labels(self.path, labels, point_order)
            self._labels = labels
            self._signature = self._stat_signature()
            return len(labels)

    def rename_point(self, old: str, new: str, point_order: list[str] | None = None) -> int:
        """Rename a point in every video; returns the number of rows changed. Never merges two points."""
        with self._lock:
            self._reload_if_changed()
            if any(k[2] == new for k in self._labels):
                raise ValueError(f"point {new!r} already has labels")
            labels = {(v, f, new if p == old else p): lab for (v, f, p), lab in self._labels.items()}
            changed = sum(1 for k in self._labels if k[2] == old)
            if changed:
                write_labels(self.path, labels, point_order)
                self._signature = self._stat_signature()
            self._labels = labels
            return changed
