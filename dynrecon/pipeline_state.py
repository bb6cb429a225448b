"""`WS/pipeline.json`: which stages of `dynrecon run` are up to date.

Per stage it keeps a hash of the stage's inputs (file contents by role, and its options) and of each output file,
so that a rerun skips a stage whose inputs and outputs are unchanged (`dynrecon.pipeline`; format in
docs/formats.md).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from dynrecon.atomic import atomic_write_text

log = logging.getLogger(__name__)

STATE_NAME = "pipeline.json"
_HASH_CHUNK = 1 << 20

__all__ = ["STATE_NAME", "State", "file_hash", "inputs_key"]


def file_hash(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(_HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _plain(value: Any) -> Any:
    """Options as JSON-able values (enums by value, paths as strings, dataclasses as dicts)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if callable(value):
        return None  # monitors and callbacks do not change results
    return value


def inputs_key(files: dict[str, Path], settings: Any) -> str:
    """Hash of the contents of `files` (by role) and of `settings`."""
    document = {"files": {role: file_hash(path) for role, path in sorted(files.items())}, "settings": _plain(settings)}
    return hashlib.sha256(json.dumps(document, sort_keys=True, default=str).encode()).hexdigest()


def _outputs_intact(entry: dict[str, Any], workspace: Path) -> bool:
    """Whether every output file a stage's record names is there with the hash it recorded."""
    for relative, digest in entry.get("outputs", {}).items():
        path = workspace / relative
        if not path.is_file() or file_hash(path) != digest:
            return False
    return True


class State:
    """`WS/pipeline.json`: per stage, the inputs key, output hashes, seconds and when it ran."""

    def __init__(self, workspace: Path) -> None:
        self.path = workspace / STATE_NAME
        self.stages: dict[str, dict[str, Any]] = {}
        if self.path.is_file():
            try:
                document = json.loads(self.path.read_text(encoding="utf-8"))
            except (OSError, ValueError, RecursionError):  # ValueError: also undecodable bytes, huge ints
                log.warning("%s is not valid JSON; every stage runs again", self.path)
                document = {}
            stages = document.get("stages", {}) if isinstance(document, dict) else None
            if not isinstance(stages, dict):
                log.warning("%s has no 'stages' object; every stage runs again", self.path)
                stages = {}
            # An entry of the wrong shape only means that stage runs again; it must not crash up_to_date.
            self.stages = {name: entry for name, entry in stages.items() if self._valid_entry(entry)}

    @staticmethod
    def _valid_entry(entry: Any) -> bool:
        """A stage entry as `record` writes it: an inputs key and output paths -> hashes."""
        outputs = entry.get("outputs", {}) if isinstance(entry, dict) else None
        return (
            isinstance(entry, dict)
            and isinstance(entry.get("inputs"), str)
            and isinstance(outputs, dict)
            and all(isinstance(k, str) and isinstance(v, str) for k, v in outputs.items())
        )

    def up_to_date(self, name: str, key: str, workspace: Path) -> bool:
        entry = self.stages.get(name)
        if not entry or entry.get("inputs") != key or "failed" in entry:
            return False
        return _outputs_intact(entry, workspace)

    def record(self, name: str, key: str, outputs: list[Path], workspace: Path, seconds: float) -> None:
        self.stages[name] = {
            "inputs": key,
            "outputs": {str(p.relative_to(workspace)): file_hash(p) for p in outputs},
            "seconds": round(seconds, 3),
            "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        self.save()

    def record_failure(
        self, name: str, key: str, failure: dict[str, str], outputs: list[Path], workspace: Path
    ) -> None:
        """Stage `name` failed on inputs `key` (`failure`: what it said); `outputs`: the files saying why, whose
        hashes tie the record to them."""
        self.stages[name] = {
            "inputs": key,
            "outputs": {str(p.relative_to(workspace)): file_hash(p) for p in outputs if p.is_file()},
            "failed": failure,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        self.save()

    def failed_before(self, name: str, key: str, workspace: Path) -> dict[str, str] | None:
        """What stage `name` said when it failed on these same inputs, its files unchanged since; else None."""
        entry = self.stages.get(name)
        failure = entry.get("failed") if entry and entry.get("inputs") == key else None
        if not isinstance(failure, dict) or not all(isinstance(v, str) for v in failure.values()):
            return None
        return failure if entry is not None and _outputs_intact(entry, workspace) else None

    def output_hash(self, name: str, path: Path, workspace: Path) -> str | None:
        """The hash stage `name` recorded for its output `path` (in `workspace`), None without a record."""
        return self.stages.get(name, {}).get("outputs", {}).get(str(path.relative_to(workspace)))

    def forget(self, name: str) -> None:
        if self.stages.pop(name, None) is not None:
            self.save()

    def save(self) -> None:
        atomic_write_text(self.path, json.dumps({"version": 1, "stages": self.stages}, indent=1) + "\n")
