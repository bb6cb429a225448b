"""Hostile-input-safe pieces shared by the file readers: CSV records, JSON loading, frame numbers, video names.

Every failure is an InputError naming the file, so a broken or malicious file never shows a traceback.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from dynrecon.errors import InputError
from dynrecon.names import first_repeated

MAX_FRAME = 2**31  # frame numbers are 0 <= frame < MAX_FRAME: they fit int32 indices and int64 arithmetic


def read_text(path: Path, *, missing_fix: str | None = None) -> str:
    """The UTF-8 text of `path`; a missing file, a folder or unreadable bytes are InputErrors."""
    try:
        return path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows editors) is not content
    except FileNotFoundError:
        raise InputError(path, "file not found", fix=missing_fix) from None
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a file", fix="give the path of a file") from None
    except UnicodeDecodeError:
        raise InputError(path, "not UTF-8 text", fix="save the file as UTF-8") from None
    except OSError as error:
        raise InputError(path, f"cannot read: {error.strerror or error}") from None


def loads_json(text: str, path: Path, *, fix: str | None = None) -> Any:
    """Parse JSON text from `path`; syntax errors, huge integers and deep nesting are InputErrors."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        header = text.lstrip().split("\n", 1)[0].strip().lower()
        if error.pos == len(text) - len(text.lstrip()) and "," in header and header[:1] not in "{[":
            # a spreadsheet CSV given where JSON was wanted (the tracks for the cameras): say what it is
            raise InputError(
                path, f"is a CSV file (its first line: {header[:60]!r}), not JSON", fix=fix or "give the JSON file"
            ) from None
        raise InputError(
            path, f"invalid JSON: {error.msg}", where=f"{error.lineno}:{error.colno}", fix=fix or "fix the JSON syntax"
        ) from None
    except ValueError:  # an integer literal of more than 4300 digits
        raise InputError(path, "invalid JSON: an integer of more than 4300 digits", fix=fix) from None
    except RecursionError:
        raise InputError(path, "invalid JSON: nested too deeply", fix=fix) from None


def read_json(path: Path, *, missing_fix: str | None = None, fix: str | None = None) -> Any:
    return loads_json(read_text(path, missing_fix=missing_fix), path, fix=fix)


def parse_frame(text: str, path: Path, where: str) -> int:
    """A frame number cell of a CSV file: an integer 0 <= frame < 2^31."""
    if "_" in text:  # int() reads 1_000 as 1000: a typo, not a frame number
        raise InputError(path, f"frame {shown(text)} is not an integer", where=where)
    try:
        frame = int(text)
    except ValueError:
        if text.strip().lstrip("+-").isdigit():  # over 4300 digits: int() refuses to convert it
            raise InputError(
                path,
                f"frame of {len(text.strip())} digits is too large",
                where=where,
                fix=f"frame numbers are below 2^31 = {MAX_FRAME}",
            ) from None
        raise InputError(path, f"frame {shown(text)} is not an integer", where=where) from None
    return check_frame(frame, path, where)


def check_frame(frame: Any, path: Path | None, where: str, *, name: str = "frame") -> int:
    """A frame number that must be an int (not a bool) with 0 <= frame < 2^31."""
    if not isinstance(frame, int) or isinstance(frame, bool):
        raise InputError(path, f"{name} {shown(frame)} is not an integer", where=where)
    if frame < 0:
        raise InputError(path, f"{name} {frame} is negative", where=where, fix="frames are 0-based")
    if frame >= MAX_FRAME:
        raise InputError(
            path, f"{name} {shown(frame)} is too large", where=where, fix=f"frame numbers are below 2^31 = {MAX_FRAME}"
        )
    return frame


def shown(value: Any, limit: int = 40) -> str:
    """repr() of a value from a file, short enough for a one-line message."""
    # Integers of thousands of digits would make the message unreadable (and str() refuses over 4300 digits).
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"{'-' if value < 0 else ''}~2^{value.bit_length() - 1}"
    try:
        text = repr(value)
    except (RecursionError, ValueError):  # nested hundreds deep, or a huge integer inside
        return f"<{type(value).__name__}>"
    return text if len(text) <= limit else f"{text[: limit // 2]}...({len(text)} characters)"


def csv_records(path: Path, *, missing_fix: str | None = None) -> Iterator[tuple[int, list[str]]]:
    """(first line, cells) of every record of the CSV file `path`, the header included.

    A UTF-8 BOM is dropped and CRLF, LF or CR line ends are accepted. Line numbers are those of the line where a
    record starts (csv's `line_num` is where it ends); a record spanning lines is an error naming where it starts,
    since no dynrecon CSV has cells with line breaks and it is almost always an unterminated quote. A missing file,
    a folder, bad UTF-8 and malformed CSV are InputErrors naming the line.
    """
    try:
        handle = path.open(newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(path, "file not found", fix=missing_fix) from None
    except IsADirectoryError:
        raise InputError(path, "is a folder, not a file", fix="give the path of a CSV file") from None
    except OSError as error:
        raise InputError(path, f"cannot read: {error.strerror or error}", fix="give the path of a CSV file") from None
    start = 1
    with handle:
        reader = csv.reader(handle, strict=True)  # strict: an unterminated quote is an error, not a 1000-line cell
        try:
            for row in reader:
                if reader.line_num > start:
                    raise InputError(
                        path,
                        f"a quoted cell runs from line {start} to line {reader.line_num}",
                        where=f"line {start}",
                        fix="close the quote on that line; cells cannot hold line breaks",
                    )
                yield start, row
                start = reader.line_num + 1
        except csv.Error as error:
            what = str(error)
            if "unexpected end of data" in what:
                what = "a quote opened here is never closed"
            raise InputError(path, f"malformed CSV: {what}", where=f"line {start}") from None
        except UnicodeDecodeError:
            raise InputError(path, "not UTF-8 text", where=f"near line {start}", fix="save the file as UTF-8") from None
        except OSError as error:
            raise InputError(path, f"cannot read: {error.strerror or error}") from None


def separator_hint(row: list[str]) -> str:
    """The hint for a CSV row read as one cell that holds another separator (`;`, tab, `|`), else an empty string."""
    separator = next((sep for sep in (";", "\t", "|") if len(row) == 1 and sep in row[0]), None)
    return f"; the file seems separated by {separator!r}: save it comma-separated" if separator else ""


def header_error(path: Path, header: list[str], missing: list[str], where: str, fix: str) -> InputError:
    """The error for a CSV header without the `missing` columns, with what most likely went wrong: another
    separator, or the names' case."""
    hint = separator_hint(header)
    if not hint:
        lower = {name.lower(): name for name in header}
        cased = [lower[name] for name in missing if name in lower]
        if cased:
            hint = f"; column names are lower case: found {', '.join(repr(name) for name in cased)}"
        elif path is not None and path.stem.endswith("_skeleton") and ("DLC_" in path.stem or "DeepCut_" in path.stem):
            hint = "; it is DeepLabCut's skeleton file (bone lengths and angles), not its points: import the CSV of "
            hint += "the same name without _skeleton"
    return InputError(path, f"header lacks column(s) {', '.join(missing)}{hint}", where=where, fix=fix)


def repeated_column(path: Path, header: list[str], where: str) -> None:
    """Refuse a CSV header naming a column twice: which of the two holds the values is a guess."""
    named = [name for name in header if name]  # empty names (trailing commas) are no columns
    twice = first_repeated(named)
    if twice is not None:
        raise InputError(
            path, f"column {named[twice]!r} appears twice in the header", where=where, fix="keep one of them"
        )


def finite_float(text: str) -> float | None:
    """The number in a CSV cell, or None when it is not a finite number."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def check_video_name(name: str, path: Path | None = None) -> str:
    """A video name that is safe as a folder or file name: not `.`/`..`, no path separator or control character.

    Video names become folders (`frames/<video>/`) and file names, so `..` (from `...mp4`) would write elsewhere.
    """
    return check_folder_name(
        name,
        path,
        what="video name",
        fix="rename the video file: its name without extension names the video everywhere",
    )


def check_folder_name(name: str, path: Path | None, *, what: str, fix: str) -> str:
    """`name` if it is safe as one folder or file name (see check_video_name), else an InputError naming `what`."""
    bad = None
    if not name or not name.strip():
        bad = "is empty"
    elif name in (".", "..") or set(name) <= {"."}:
        bad = "is only dots"
    elif "/" in name or "\\" in name:
        bad = "contains a path separator"
    elif any(ord(c) < 32 or ord(c) == 127 for c in name):
        bad = "contains a control character"
    if bad is not None:
        raise InputError(path, f"{what} {shown(name)} {bad}", fix=fix)
    return name
