"""`Reconstruction.write`: the recording, written beside points3d.csv in a second process, is published only when
both succeeded, and no temporary file is left either way (reconstruct/stage.py, dynrecon/beside.py)."""

from __future__ import annotations

import errno
import time
from pathlib import Path

import pytest
from synthetic_motion import smooth_motion

from reconstruct import stage
from reconstruct.stage import solve
from simulation.simulate import SimulationOptions, simulate_capture


@pytest.fixture(scope="module")
def solved():
    capture = simulate_capture(smooth_motion(60, 6, seed=4), 60.0, SimulationOptions(seed=4))
    return solve(capture.cameras, capture.tracks)


def test_a_written_solve_has_its_recording_and_no_leftovers(solved, tmp_path: Path) -> None:
    solved.write(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "points3d.csv",
        "recording.rrd",
        "report.json",
        "sequencing.json",
    ]
    assert (tmp_path / "recording.rrd").stat().st_size > 0
    assert "recording" in solved.report["timings"]


def test_a_failed_write_publishes_no_recording(solved, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full_disk(*_: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(stage, "write_sequencing", full_disk)
    with pytest.raises(OSError, match="No space left"):
        solved.write(tmp_path)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "recording.rrd" not in names and "report.json" not in names
    assert not [name for name in names if name.startswith(".")], names  # no pending or temporary file


def test_a_writer_stopped_without_its_cleanup_leaves_no_temporary_file(
    solved, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A writer stopped inside native code (or killed after the grace period) cannot remove its own temporary file:
    the caller removes it."""

    def stuck_writer(self: object, path: Path) -> float:
        (path.parent / f".{path.name}.abc123.tmp").write_bytes(b"partial")
        time.sleep(3)  # a forked writer is stopped here (SIGTERM); a thread runs on: neither cleans up
        return 0.0

    def full_disk(*_: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(stage.Reconstruction, "_timed_recording", stuck_writer)
    monkeypatch.setattr(stage, "write_sequencing", full_disk)
    with pytest.raises(OSError, match="No space left"):
        solved.write(tmp_path)
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
