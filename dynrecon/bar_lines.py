"""Progress bars written into a log file: each redraw a line of its own, never the start of a log record's line.

On a terminal tqdm redraws a bar in place (a carriage return, then the bar); in a file the redraws pile up on one
line, and the next log record or error message continues that line. `LineStream` wraps such a stream: a write
that begins with a carriage return is a redraw, written as its last state on a line of its own; a blank redraw (a
bar clearing itself) and tqdm's moves between bar rows are dropped; other text passes (CRLF line ends as LF).
"""

from __future__ import annotations

import contextlib
import re
import sys
from collections.abc import Iterable, Iterator
from typing import Any, TextIO

__all__ = ["LineStream", "bar_lines"]

_CURSOR = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")  # tqdm's cursor moves between the rows of nested bars


class LineStream:
    """`stream` with tqdm's redraws as lines (see the module); everything else is `stream`'s own."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self._after_bar = False  # the last text written was a bar's line: a newline that closes it is dropped
        self._line_start = True  # the last text written ended its line
        # line ends written at a line's start: tqdm's move down to a lower bar's row, unless text follows
        self._held = ""

    def write(self, text: str) -> int:
        if text.startswith("\r"):  # tqdm's redraws and clears begin with a carriage return; a message's CRLF does not
            self._held = ""
            last = _CURSOR.sub("", text.rsplit("\r", 1)[-1]).rstrip()
            if last:
                self.stream.write(last + "\n")
                self._after_bar = self._line_start = True
            return len(text)
        if _CURSOR.search(text) or (self._after_bar and not text.strip("\n")):
            return len(text)  # a move between bar rows, or the line end of a bar kept on close
        if text and not text.strip("\n") and self._line_start:
            self._held += text
            return len(text)
        if self._held:
            self.stream.write(self._held)
            self._held = ""
        text = text.replace("\r\n", "\n")
        if text:
            self._after_bar = False
            self._line_start = text.endswith("\n")
        return self.stream.write(text)

    def writelines(self, lines: Iterable[str]) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return False

    def __getattr__(self, name: str) -> Any:  # fileno, encoding, ...: the wrapped stream's
        return getattr(self.stream, name)


@contextlib.contextmanager
def bar_lines() -> Iterator[None]:
    """`sys.stderr` as a LineStream while inside, where it is not a terminal (a log file, a pipe)."""
    stream = sys.stderr
    if isinstance(stream, LineStream) or _is_terminal(stream):
        yield
        return
    sys.stderr = LineStream(stream)
    try:
        yield
    finally:
        sys.stderr = stream


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # a closed or odd stream: leave it as it is
        return True
