"""SIGTERM on a command that loaded pycolmap: a clean stop (exit 143, one line), not pycolmap's native stack trace."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from dynrecon.lock import LOCK_NAME

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "data_samples" / "video_sample"


def test_sigterm_during_register_stops_cleanly(tmp_path: Path) -> None:
    out = tmp_path / "ws"
    code = "import sys; from dynrecon.cli import main; sys.exit(main(sys.argv[1:]))"
    videos = [str(path) for path in sorted(SAMPLE.glob("*.mp4"))]
    process = subprocess.Popen(
        [sys.executable, "-c", code, "register", *videos, "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )
    deadline = time.monotonic() + 120
    while not (out / "sfm").exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)  # pycolmap is loaded and a stage runs once sfm/ exists
    time.sleep(1.0)
    assert process.poll() is None, "register ended before it could be stopped"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert err.rstrip().splitlines()[-1] == "stopped (SIGTERM)"
    assert "*** SIGTERM received" not in err and "Traceback" not in err
    assert not (out / LOCK_NAME).exists()


def test_the_handler_is_restored_for_a_caller_in_python(tmp_path: Path) -> None:
    from dynrecon.cli import main

    before = signal.getsignal(signal.SIGTERM)
    missing = str(tmp_path / "missing.csv")
    assert main(["solve", "--cameras", missing, "--tracks", missing, "--out", str(tmp_path / "out")]) == 2
    assert signal.getsignal(signal.SIGTERM) is before
