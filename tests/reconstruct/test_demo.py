from pathlib import Path

from rrd_reader import entities, verify

from dynrecon.cli import main
from reconstruct.demo import fresh_folder

SAMPLES = Path(__file__).resolve().parents[2] / "data_samples"


def test_demo_runs_end_to_end_and_reports_accuracy(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "<10:" in printed and str(out / "recording.rrd") in printed
    share_under_10 = float(printed.split("<10:")[1].split("%")[0])
    assert share_under_10 > 90.0
    assert {"/world/points", "/world/cameras/cam0"} <= entities(out / "recording.rrd")
    verify(out / "recording.rrd")


def test_fresh_folder_never_reuses_results(tmp_path):
    first = fresh_folder(tmp_path / "demo")
    (first / "points3d.csv").write_text("x")
    second = fresh_folder(tmp_path / "demo")
    assert second != first and second.name == "demo-2"


def test_sample_is_what_its_generator_makes(tmp_path, monkeypatch):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_walker", SAMPLES / "make_walker.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from reconstruct.mocap import read_mocap

    sample = read_mocap(SAMPLES / "walker.trc")
    assert sample.xyz.shape == module.walker().shape
    assert abs(sample.xyz - module.walker()).max() < 1e-6
