"""The house rules that tools check: ruff lint, ruff format and mypy are clean on the whole tree (pyproject.toml)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


@pytest.mark.skipif(
    shutil.which("ruff") is None and _run("ruff", "--version").returncode != 0,
    reason="ruff is not installed (pip install -e '.[test]')",
)
@pytest.mark.parametrize("command", [("ruff", "format", "--check", "."), ("ruff", "check", ".")])
def test_ruff(command: tuple[str, ...]) -> None:
    result = _run(*command)
    assert result.returncode == 0, (
        f"`{' '.join(command)}` is not clean (run `ruff format .` / `ruff check --fix .`):\n"
        f"{result.stdout[-3000:]}{result.stderr[-2000:]}"
    )


@pytest.mark.slow
def test_mypy() -> None:
    pytest.importorskip("mypy", reason="mypy is not installed (pip install -e '.[test]')")
    result = _run("mypy")
    assert result.returncode == 0, f"mypy is not clean:\n{result.stdout[-3000:]}{result.stderr[-2000:]}"
