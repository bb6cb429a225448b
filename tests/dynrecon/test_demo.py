"""`dynrecon demo`: the video pipeline on a 1 s cut of the embedded sample (the full demo is measured by hand, see
the README), the --simulated variant, fresh folders and a clear error for an incomplete sample."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rrd_reader import entities, timelines, verify

from data_samples.make_video_sample import cut_sample
from dynrecon.cli import main
from dynrecon.demo import fresh_folder

SAMPLES = Path(__file__).resolve().parents[2] / "data_samples"
VIDEO_SAMPLE = SAMPLES / "video_sample"


def _share_under_10(printed: str) -> float:
    return float(printed.split("<10:")[1].split("%")[0])


@pytest.fixture(scope="module")
def cut(tmp_path_factory) -> Path:
    if not (VIDEO_SAMPLE / "cam0.mp4").is_file():
        pytest.skip("data_samples/video_sample is not generated")
    return cut_sample(tmp_path_factory.mktemp("sample"), seconds=1.0)


@pytest.mark.slow
def test_video_demo_runs_the_pipeline_and_reports_accuracy(cut, tmp_path, capsys):
    out = tmp_path / "demo"
    # One COLMAP thread: the same cameras on every run. On this short cut, registrations on several threads scored
    # anywhere from 21 to 77 % < 10 mm (dynrecon.demo.DemoOptions.sfm_threads).
    assert main(["demo", "--out", str(out), "--sample", str(cut), "--threads", "1"]) == 0
    printed = capsys.readouterr().out
    assert f"rerun {out / 'recording.rrd'}" in printed
    assert "similarity" in printed  # says that the SfM world was aligned to the truth before scoring
    # The 1 s cut: 30 + 24 + 20 frames, 18 joints, every frame registered and scored.
    accuracy = json.loads((out / "accuracy.json").read_text())
    assert accuracy["count"] == (30 + 24 + 20) * 18
    assert accuracy["unreconstructed"] == 0
    assert _share_under_10(printed) == pytest.approx(100 * accuracy["share_under"][0], abs=0.01)
    assert _share_under_10(printed) > 50.0
    assert accuracy["median"] < 12.0
    found = entities(out / "recording.rrd")
    for name in ("/world/background", "/world/points", *(f"/world/cameras/cam{i}/image" for i in range(3))):
        assert name in found, name
    assert timelines(out / "recording.rrd") == {"global_time", "frame:cam0", "frame:cam1", "frame:cam2"}
    checked = verify(out / "recording.rrd")
    assert checked.returncode == 0, checked.stderr


def test_simulated_demo_runs_end_to_end_and_reports_accuracy(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--simulated", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "<10:" in printed and f"rerun {out / 'recording.rrd'}" in printed
    assert _share_under_10(printed) > 90.0
    assert {"/world/points", "/world/cameras/cam0"} <= entities(out / "recording.rrd")
    checked = verify(out / "recording.rrd")
    assert checked.returncode == 0, checked.stderr


def test_incomplete_sample_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "sample").mkdir()
    assert main(["demo", "--out", str(tmp_path / "demo"), "--sample", str(tmp_path / "sample")]) == 2
    err = capsys.readouterr().err  # a user's --sample: named as such, not as the embedded sample
    assert f"{tmp_path / 'sample' / 'cam0.mp4'}: not found" in err and "--sample names a folder" in err
    assert not (tmp_path / "demo").exists()  # refused before a folder was made


def test_fresh_folder_never_reuses_results(tmp_path):
    first = fresh_folder(tmp_path / "demo")
    (first / "points3d.csv").write_text("x")
    second = fresh_folder(tmp_path / "demo")
    assert second != first and second.name == "demo-2"
    (tmp_path / "afile").write_text("x")  # a file where the folder would be: the next free name, no traceback
    assert fresh_folder(tmp_path / "afile") == tmp_path / "afile-2" and (tmp_path / "afile-2").is_dir()


def test_sample_is_what_its_generator_makes(tmp_path, monkeypatch):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_walker", SAMPLES / "make_walker.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from reconstruct.outputs.mocap import read_mocap

    sample = read_mocap(SAMPLES / "walker.trc")
    assert sample.xyz.shape == module.walker().shape
    assert abs(sample.xyz - module.walker()).max() < 1e-6
