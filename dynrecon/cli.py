"""The `dynrecon` command: a thin argparse layer over the stages' `run` functions.

Each package contributes its subcommands through an `add_commands(subparsers)` function in its `cli` module; a
subcommand sets `func(args) -> int`. User errors (`DynreconError`) are caught here, once, and shown as one line.

Startup stays fast: a `cli` module imports only argparse-level modules at its top, and the stage in its handlers. A
module whose parsers need heavy modules for their defaults (the solver's, the simulators') also lists its commands
and their one-line help in `COMMANDS`; its `add_commands` then runs only when one of those commands is chosen, and
`dynrecon --help` shows the list without loading it.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NoReturn

from dynrecon import __version__
from dynrecon.bar_lines import bar_lines
from dynrecon.beside import quiet_tqdm_monitor
from dynrecon.errors import DynreconError
from dynrecon.lock import OutputLock

# Modules whose `add_commands` registers subcommands, in the order they appear in `--help`.
COMMAND_MODULES = (
    "sfm.cli",
    "labeling.cli",
    "tracking.cli",
    "reconstruct.cli",
    "simulation.cli",
    "dynrecon.pipeline_cli",
    "batch.cli",
)

log = logging.getLogger("dynrecon")

WRITERS = ("run", "register", "solve", "batch", "export")  # commands that hold OUT/.dynrecon.lock while they write


class Terminated(KeyboardInterrupt):
    """SIGTERM (`kill`, `timeout`, a scheduler), raised where Python next runs: it unwinds like Ctrl+C, so locks are
    released, a child process is stopped and earlier results are kept; a subclass so every Ctrl+C path handles it."""


def _terminated(signum: int, frame: object) -> None:
    raise Terminated


@contextlib.contextmanager
def sigterm_as_stop() -> Iterator[None]:
    """Handle SIGTERM as a stop request while the command runs. pycolmap's crash handler claims SIGTERM when it loads
    and prints a native stack trace for it, so pycolmap is loaded first and its handler replaced (a later import does
    not install it again); the Python handler of before is set again afterwards, for a caller of `main` in Python.
    Off the main thread nothing is touched: only the main thread may set handlers, and loading pycolmap there would
    replace the caller's own handler for good."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    import pycolmap  # noqa: F401

    previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class OneLineParser(argparse.ArgumentParser):
    """Option errors on one line, as every other user error: the subcommands' usage runs to 20 lines and more."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The full parser of `command` (all of them when None); the others' parsers are placeholders with their help
    line where their module lists them in `COMMANDS`."""
    parser = OneLineParser(
        prog="dynrecon",
        description="3D trajectories of moving points from several unsynchronized videos.",
    )
    parser.add_argument("--version", action="version", version=f"dynrecon {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in COMMAND_MODULES:
        module = importlib.import_module(module_name)
        listed: dict[str, str] | None = getattr(module, "COMMANDS", None)
        if listed is None or command is None or command in listed:
            module.add_commands(subparsers)
        else:
            for name, help_line in listed.items():
                subparsers.add_parser(name, help=help_line)
    return parser


def chosen_command(argv: Sequence[str]) -> str:
    """The subcommand named in `argv` (the top-level options take no value, so it is the first other word)."""
    return next((word for word in argv if not word.startswith("-")), "")


class _OnceEach(logging.Filter):
    """Each distinct warning once: a step that runs again (the clocks of every path the solve tries, a fold of
    the tracks) repeats its warnings word for word, which buried the few that differ."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[tuple[str, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        key = (record.name, record.getMessage())
        if key in self.seen:
            return False
        self.seen.add(key)
        return True


def configure_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else logging.DEBUG if verbose >= 2 else logging.INFO
    root = logging.getLogger()
    configured = bool(root.handlers)  # by a caller of main() (a test's capture): its handlers are left as they are
    logging.basicConfig(level=level, format="%(levelname).1s %(name)s: %(message)s", stream=sys.stderr)
    for handler in root.handlers:
        once = [f for f in handler.filters if isinstance(f, _OnceEach)]
        for each in once:  # a command run again in the same process (a benchmark's) says its warnings again
            each.seen.clear()
        if not configured and not once:
            handler.addFilter(_OnceEach())
    # Third-party chatter stays at warning level unless the user asks for debug output.
    if verbose < 2:
        for noisy in ("PIL", "matplotlib", "urllib3"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    # tqdm reads its TQDM_* settings when it is imported: set before quiet_tqdm_monitor imports it
    if quiet:  # -q: only warnings and errors, no progress bars either
        os.environ.setdefault("TQDM_DISABLE", "1")
    if not sys.stderr.isatty():  # a log file keeps every redraw of a bar: one every 10 s is a record enough,
        os.environ.setdefault("TQDM_MININTERVAL", "10")
        os.environ.setdefault("TQDM_DELAY", "10")  # and a step shorter than that leaves no bar in it
    quiet_tqdm_monitor()  # its thread would keep dynrecon/beside.py from forking


def _say(message: str, *, stopped: bool = False) -> None:
    """The last line on stderr. `tqdm.write` clears this process's progress bars first; a stop also starts a line of
    its own, since it may cut a bar short (a child process's, sfm/isolated.py, too), which has no line end then."""
    from tqdm import tqdm

    tqdm.write("\n" + message if stopped else message, file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(chosen_command(argv))
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    with bar_lines():  # off a terminal, a log record never continues a progress bar's line
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    configure_logging(args.verbose, args.quiet)
    try:
        with sigterm_as_stop():
            if args.command in WRITERS:  # two writers of one folder would mix their files, each told it succeeded
                with OutputLock(Path(args.out), workspace=args.command == "run"):
                    return int(args.func(args) or 0)
            return int(args.func(args) or 0)
    except DynreconError as error:
        _say(f"dynrecon {args.command}: error: {error}")
        return 2
    except OSError as error:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        # the machine's state, not a bug: one line (a failed write or flush names no file: the output folder then)
        where = error.filename or getattr(args, "out", None) or "the output folder"
        _say(f"dynrecon {args.command}: error: {where}: no space left on the device (free some, then run again)")
        return 2
    except Terminated:
        _say("stopped (SIGTERM)", stopped=True)
        raise SystemExit(128 + signal.SIGTERM) from None  # a request to end the process, also one calling `main`
    except KeyboardInterrupt:
        _say("interrupted", stopped=True)
        return 128 + signal.SIGINT


if __name__ == "__main__":  # `python -m dynrecon.cli` as well as `python -m dynrecon`
    raise SystemExit(main())
