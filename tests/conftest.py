"""Shared fixtures. Tests that need the real data beside the checkout (`../shared`) skip when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dynrecon.beside import quiet_tqdm_monitor

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNRECON_SHARED", REPO.parent / "shared"))

# Single-threaded BLAS: measured faster than 2 threads on the small matrices of these tests, and the suite may run
# beside other work on 2 cores.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
quiet_tqdm_monitor()  # as the command line does: no monitor thread, so that solves fork where they would


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Modules with a slow test first, each kept whole and in collection order: with `--dist loadscope
    --no-loadscope-reorder` the two workers start on the long modules and the many short ones fill in at the end,
    so that neither waits idle on the other's last long module (xdist's own order, by test count, put the longest
    single-test modules last)."""
    slow = {item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.nodeid.split("::")[0] not in slow)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """`../shared` (real data); skips the test with the reason when it is absent."""
    if not (SHARED / "data").is_dir():
        pytest.skip(f"needs the shared data folder {SHARED} (absent in a user's clone)")
    return SHARED
