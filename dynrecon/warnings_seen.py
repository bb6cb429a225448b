"""The warnings a long command logged, kept to be repeated at its end: `dynrecon run` logs dozens of lines, and a
warning that decides how to read the results (a calibration's units guessed, a camera's fit) was lost among them."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator


class WarningsSeen(logging.Handler):
    """Each distinct warning (or error) message logged while installed, in order."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.add(record.getMessage())

    def add(self, message: str) -> None:
        """Keep `message` unless it is kept already (a forked worker's, `dynrecon.beside`)."""
        if message not in self.messages:
            self.messages.append(message)


@contextlib.contextmanager
def warnings_seen() -> Iterator[WarningsSeen]:
    """Collect the warnings logged in the block (by any logger that propagates to the root)."""
    handler = WarningsSeen()
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield handler
    finally:
        root.removeHandler(handler)


__all__ = ["WarningsSeen", "warnings_seen"]
