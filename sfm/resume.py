"""Resuming an interrupted `register`: each finished step (keyframes, extraction, matching, mapping) is recorded
in `WS/sfm/steps.json` with a key computed from its inputs; a later run reuses the step's output when the key is
unchanged, instead of computing it again. A step that was interrupted has no record and runs again.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from dynrecon.atomic import atomic_write_text

STEPS_FILE = "steps.json"


def input_key(*parts: Any) -> str:
    """A digest of JSON-able inputs (paths and enums as text)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.blake2b(text.encode("utf-8"), digest_size=16).hexdigest()


def files_key(paths: list[Path]) -> str:
    """A digest of the files' names and contents (missing files count as absent)."""
    digest = hashlib.blake2b(digest_size=16)
    for path in paths:
        digest.update(str(path).encode("utf-8") + b"\0")
        if path.exists():
            digest.update(path.read_bytes())
        digest.update(b"\1")
    return digest.hexdigest()


class StepLog:
    """The finished steps of a workspace: step -> {key, result}; written after every change."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / STEPS_FILE
        self.steps: dict[str, dict[str, Any]] = {}
        if self.path.exists():
            try:
                self.steps = json.loads(self.path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                self.steps = {}  # an unreadable log only costs the recomputation
        self.reused: list[str] = []

    def result(self, step: str, key: str) -> Any | None:
        """The recorded result of `step` when it was finished with the same inputs, else None."""
        entry = self.steps.get(step)
        if entry is None or entry.get("key") != key:
            return None
        return entry.get("result")

    def reuse(self, step: str, result: Any) -> Any:
        """`result`, noting that `step` was not run again (the report lists these)."""
        self.reused.append(step)
        return result

    def record(self, step: str, key: str, result: Any) -> None:
        self.steps[step] = {"key": key, "result": result}
        self._write()

    def forget(self, *steps: str) -> None:
        """Drop these steps' records (their outputs are about to be replaced)."""
        for step in steps:
            self.steps.pop(step, None)
        self._write()

    def _write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path, json.dumps(self.steps, indent=1) + "\n")
