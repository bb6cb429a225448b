"""`dynrecon run` repeats its warnings at the end, once each: dozens of log lines hid one that decided how to read the
results (a calibration's units guessed: a user's report, 2026-11-30)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from dynrecon import cli
from dynrecon.pipeline import PipelineResult
from dynrecon.warnings_seen import warnings_seen


def test_distinct_warnings_are_kept_in_order() -> None:
    with warnings_seen() as seen:
        logging.getLogger("sfm.calibration").warning("units read in %s", "millimetres")
        logging.getLogger("reconstruct.fit").info("not a warning")
        logging.getLogger("reconstruct.fit").warning("a camera misses")
        logging.getLogger("sfm.calibration").warning("units read in %s", "millimetres")
    logging.getLogger("x").warning("after the block")
    assert seen.messages == ["units read in millimetres", "a camera misses"]


@pytest.mark.parametrize("quiet", [False, True])
def test_run_repeats_them_at_its_end(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], quiet: bool
) -> None:
    import dynrecon.pipeline

    def stages(videos: list[Path], out: Path, options: object) -> PipelineResult:
        logging.getLogger("sfm.calibration").warning("cal.toml: translations read in millimetres (--units m ...)")
        return PipelineResult(workspace=out, stages=[])

    monkeypatch.setattr(dynrecon.pipeline, "run_stages", stages)
    flags = ["-q"] if quiet else []
    assert cli.main([*flags, "run", "a.mp4", "b.mp4", "--out", str(tmp_path / "ws")]) == 0
    out = capsys.readouterr().out
    if quiet:  # the warnings were all there was to read
        assert "warning(s)" not in out
    else:
        assert "1 warning(s) in the log above, once each:\n  - cal.toml: translations read in millimetres" in out
