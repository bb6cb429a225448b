"""Exceptions for mistakes in a user's input.

They carry everything needed for a one-line message: which file, where in it, what is wrong and what to do. The CLI
catches `DynreconError` once and prints `str(error)`; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from pathlib import Path


class DynreconError(Exception):
    """Base class of all errors caused by user input or environment, shown as one line."""

    def __reduce__(self) -> tuple[object, ...]:
        # Subclasses take their own constructor arguments: a copy (pickled from a worker process) is rebuilt from
        # the message and the attributes, not by calling __init__ with the message alone.
        return (_rebuild, (type(self), self.args, self.__dict__))


def _rebuild(cls: type[DynreconError], args: tuple[object, ...], state: dict[str, object]) -> DynreconError:
    error = cls.__new__(cls)
    Exception.__init__(error, *args)
    error.__dict__.update(state)
    return error


class InputError(DynreconError):
    """A problem in an input file: `file:where: what (fix)`."""

    def __init__(self, path: str | Path | None, what: str, *, where: str | None = None, fix: str | None = None):
        self.path = Path(path) if path is not None else None
        self.what = what
        self.where = where
        self.fix = fix
        super().__init__(self._format())

    def _format(self) -> str:
        location = str(self.path) if self.path is not None else None  # None: an option's value, named in `what`
        if self.where:
            location = f"{location or 'input'}:{self.where}"
        message = f"{location}: {self.what}" if location else self.what
        if self.fix:
            message = f"{message} ({self.fix})"
        return message


class NotEnoughDataError(DynreconError):
    """The input is valid but cannot support a reconstruction (e.g. fewer than two videos)."""
