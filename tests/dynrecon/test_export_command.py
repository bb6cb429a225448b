"""`dynrecon export`: a solve's points as TRC and C3D without `run` (a calibration and tracks shared without their
videos reached points3d.csv but no export: a user's report, 2026-11-30)."""

from __future__ import annotations

from pathlib import Path

import pytest
from synthetic_motion import simulated_phones

from dynrecon.cli import main
from reconstruct.outputs.mocap import read_mocap


def test_export_writes_what_run_writes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim = simulated_phones(tmp_path / "phones")
    solved = tmp_path / "solved"
    solve = ["solve", "--cameras", str(sim / "cameras.json"), "--tracks", str(sim / "tracks.csv"), "--out", str(solved)]
    assert main([*solve, "--no-recording"]) == 0
    capsys.readouterr()
    assert main(["export", str(solved), "--cameras", str(sim / "cameras.json"), "--units", "mm"]) == 0
    assert "points.trc" in capsys.readouterr().out
    trc = read_mocap(solved / "points.trc")
    assert trc.xyz.shape[1] == 8 and trc.rate > 0  # the simulation's 8 points
    assert (solved / "points.c3d").stat().st_size > 0
    assert (solved / "points.trc").read_text().splitlines()[2].split("\t")[4] == "mm"


def test_units_given_to_an_arbitrary_scale_are_said_to_be_a_label(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    """Cameras `register` posed without --scale or --board have an arbitrary scale: `--units m` labels the
    exports, and a warning says they are not metres (a helper's LED wand was 1.28 calibration-metres per unit)."""
    import json
    import os

    sim = simulated_phones(tmp_path / "phones")
    solved = tmp_path / "solved"
    solve = ["solve", "--cameras", str(sim / "cameras.json"), "--tracks", str(sim / "tracks.csv"), "--out", str(solved)]
    assert main([*solve, "--no-recording"]) == 0
    export = ["export", str(solved), "--cameras", str(sim / "cameras.json"), "--units", "m"]
    assert main(export) == 0
    assert "arbitrary scale" not in caplog.text  # no registration's report: a calibration's cameras
    for units, warned in ((None, True), ("m", False)):
        caplog.clear()
        (sim / "register_report.json").write_text(json.dumps({"subject": {"units": units}}))
        assert main(export) == 0
        assert ("register gave these cameras an arbitrary scale" in caplog.text) is warned, caplog.text
    # a report older than the cameras is another registration's (a calibration imported over it): nothing said
    (sim / "register_report.json").write_text(json.dumps({"subject": {"units": None}}))
    stamp = (sim / "cameras.json").stat().st_mtime
    os.utime(sim / "register_report.json", (stamp - 60, stamp - 60))
    caplog.clear()
    assert main(export) == 0
    assert "arbitrary scale" not in caplog.text
    capsys.readouterr()


def test_export_names_what_is_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(tmp_path), "--cameras", str(tmp_path / "cameras.json"), "--units", "m"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("points3d.csv: file not found (give the folder `dynrecon solve --out` wrote, and its cameras)")
    with pytest.raises(SystemExit):  # --units is required: the exports' unit label is the user's to say
        main(["export", str(tmp_path), "--cameras", str(tmp_path / "cameras.json")])
    capsys.readouterr()
    assert main(["export", str(tmp_path), "--cameras", str(tmp_path / "cameras.json"), "--units", "feet"]) == 2
    assert "--units 'feet' is not a unit (use one of" in capsys.readouterr().err
