"""One tracked point (a ball, a drone, an insect) must solve in seconds: the seed solve once stalled for minutes on
a few hundred frames of one point (issue 22)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BOUND_S = 20.0  # generous on 2 shared cores: the target for 800 frames is 10 s for the whole solve


@pytest.mark.xfail(reason="issue 22: the P = 1 seed solve still stalls (docs/measurements.md)", strict=True)
def test_one_point_solves_within_bound(tmp_path: Path) -> None:
    def dynrecon(*args: str, timeout: float) -> None:
        subprocess.run([sys.executable, "-m", "dynrecon", "-q", *args], check=True, timeout=timeout, cwd=ROOT)

    dynrecon("simulate", "--mode", "flight", "--duration", "3", "--seed", "1", "--out", str(tmp_path), timeout=60)
    cmd = ["solve", "--cameras", str(tmp_path / "cameras.json"), "--tracks", str(tmp_path / "tracks.csv")]
    dynrecon(*cmd, "--out", str(tmp_path), "--refinement", "none", "--no-recording", timeout=BOUND_S)
    assert (tmp_path / "points3d.csv").exists()
