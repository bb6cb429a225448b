"""dynrecon.bar_lines: off a terminal, progress bars' redraws are lines of their own, and a log record or an error
never continues a bar's line (a log file of `dynrecon run ... 2> run.log`)."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

from tqdm import tqdm

from dynrecon.bar_lines import LineStream

ROOT = Path(__file__).resolve().parents[2]


def test_redraws_become_lines_and_records_start_their_own() -> None:
    file = io.StringIO()
    stream = LineStream(file)
    handler = logging.StreamHandler(stream)  # type: ignore[arg-type]
    handler.setFormatter(logging.Formatter("%(levelname).1s %(message)s"))
    log = logging.getLogger("bar_lines_test")
    log.addHandler(handler)
    log.propagate = False
    try:
        with tqdm(total=4, desc="outer", file=stream, mininterval=0, leave=True) as outer:
            for k in range(4):
                with tqdm(range(2), desc="inner", file=stream, mininterval=0, leave=False) as inner:
                    for _ in inner:
                        pass
                log.warning("record %d", k)
                outer.update()
        tqdm.write("the last line", file=stream)
    finally:
        log.removeHandler(handler)
    lines = file.getvalue().split("\n")
    assert lines[-1] == ""  # ends with a line end
    lines = lines[:-1]
    assert all("\r" not in line and "\x1b" not in line and line.strip() for line in lines), lines
    records = [line for line in lines if line.startswith("W ")]
    assert records == [f"W record {k}" for k in range(4)]
    bars = [line for line in lines if not line.startswith("W ")]
    assert all(line.startswith(("outer:", "inner:")) or line == "the last line" for line in bars), bars
    assert bars[-2].startswith("outer: 100%") and bars[-1] == "the last line"  # the kept bar's last state


def test_a_lower_bar_s_row_move_is_no_blank_line_but_a_message_s_line_end_is_kept() -> None:
    file = io.StringIO()
    stream = LineStream(file)
    for text in ("I record\n", "\n", "\rinner: 50%", "\x1b[A", "I next", "\n", "\n", "I after a blank line\n"):
        stream.write(text)
    assert file.getvalue() == "I record\ninner: 50%\nI next\n\nI after a blank line\n"


def test_a_message_with_carriage_returns_is_kept_whole() -> None:
    file = io.StringIO()
    stream = LineStream(file)
    stream.write("E a line of a Windows file\r\n")
    stream.writelines(["a\rb\n", "\rbar: 10%"])
    assert file.getvalue() == "E a line of a Windows file\na\rb\nbar: 10%\n"


def test_a_command_s_log_file_has_no_bar_in_a_record_s_line(tmp_path: Path) -> None:
    """A command with bars and log records, its stderr a file: each record begins its line."""
    code = (
        "import logging, sys\n"
        "from dynrecon.cli import main\n"
        "import dynrecon.cli as cli\n"
        "def busy(args):\n"
        "    from tqdm import tqdm\n"
        "    for k in tqdm(range(3), desc='working'):\n"
        "        logging.getLogger('dynrecon.x').info('step %d', k)\n"
        "    raise cli.DynreconError('a user error')\n"
        "class P:\n"
        "    def parse_args(self, argv):\n"
        "        import argparse\n"
        "        return argparse.Namespace(command='export', func=busy, out='.', verbose=0, quiet=False)\n"
        "cli.build_parser = lambda *_: P()\n"
        "sys.exit(main(['export']))\n"
    )
    log_file = tmp_path / "run.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("TQDM_")}  # (a -q command here sets TQDM_DISABLE)
    env |= {"TQDM_DELAY": "0", "TQDM_MININTERVAL": "0"}  # bars drawn at once (after 10 s in a log by default)
    with open(log_file, "w") as err:
        done = subprocess.run([sys.executable, "-c", code], stderr=err, cwd=ROOT, check=False, env=env)
    assert done.returncode == 2
    lines = log_file.read_text().splitlines()
    assert [line for line in lines if "step" in line] == [f"I dynrecon.x: step {k}" for k in range(3)], lines
    assert lines[-1] == "dynrecon export: error: a user error"
    assert any(line.startswith("working:") for line in lines) and not any("\r" in line for line in lines)
