"""The Python example of docs/scaling.md ("From Python"), run as it stands on two small simulated captures: the
batch's graph and a graph of one's own from `dynrecon.pipeline.Stages` give the files of `dynrecon run`, byte for
byte. Dask's threaded scheduler in this process: no cluster needed for the calls themselves."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import dask
import pytest

from batch.synthetic import Inputs, SimulatedCaptureOptions, simulated_capture
from dynrecon.pipeline import PipelineResult, run_stages

DOC = Path(__file__).resolve().parents[2] / "docs" / "scaling.md"
MARKER = "<!-- tested: tests/batch/test_stages_api.py runs the next block -->"
SAME_BYTES = ("register/cameras.json", "tracks.csv", "points3d.csv", "sequencing.json", "points.trc", "points.c3d")


def _example() -> str:
    text = DOC.read_text(encoding="utf-8")
    assert MARKER in text, "docs/scaling.md lost its tested example"
    found = re.search(r"```python\n(.*?)```", text[text.index(MARKER) :], re.DOTALL)
    assert found is not None
    return found.group(1)


@pytest.fixture(scope="module")
def ran(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("example")
    for seed, name in enumerate(("monday", "tuesday"), start=4):
        options = SimulatedCaptureOptions(seed=seed, inputs=Inputs.LABELS, points=3, seconds=1.0)
        simulated_capture(root / "captures" / name, options)
    namespace: dict = {"__name__": "example"}
    # Dask's default scheduler for this process: a distributed Client that other tests closed may still be named.
    with pytest.MonkeyPatch.context() as patch, dask.config.set(scheduler="threads"):
        patch.chdir(root)
        exec(compile(_example(), str(DOC), "exec"), namespace)  # the documentation's own code, as a reader runs it
    return root, namespace


def test_the_documented_example_runs(ran: tuple[Path, dict]) -> None:
    _, namespace = ran
    outcomes, results = namespace["outcomes"], namespace["results"]
    assert [(o.capture, o.stage, o.status) for o in outcomes] == [
        ("monday", "solve", "done"),
        ("tuesday", "solve", "done"),
    ]
    assert all(isinstance(r, PipelineResult) for r in results)
    for result in results:
        assert [s.name for s in result.stages if not s.skipped] == ["track", "solve", "record", "export"]


def test_both_graphs_give_the_files_of_dynrecon_run(ran: tuple[Path, dict]) -> None:
    from dynrecon.pipeline import PipelineOptions

    root, _ = ran
    for name in ("monday", "tuesday"):
        folder = root / "captures" / name
        options = PipelineOptions(labels=folder / "labels.csv", calibration=folder / "calibration.toml")
        alone = run_stages(sorted(folder.glob("*.avi")), root / "alone" / name, options).workspace
        for relative in SAME_BYTES:
            reference = (alone / relative).read_bytes()
            assert (root / "season" / name / relative).read_bytes() == reference, f"season/{name}/{relative}"
            assert (root / "mine" / name / relative).read_bytes() == reference, f"mine/{name}/{relative}"


def test_the_stages_one_by_one_are_run_stages(ran: tuple[Path, dict], tmp_path: Path) -> None:
    """Each public stage method called in turn (the tracker swapped for a copy of the tracker's own file) writes
    what `run_stages` writes, and records every stage in pipeline.json."""
    from dynrecon.pipeline import STAGES, PipelineOptions, Stages

    root, _ = ran
    folder = root / "captures" / "monday"
    options = PipelineOptions(labels=folder / "labels.csv", calibration=folder / "calibration.toml")
    videos = sorted(folder.glob("*.avi"))
    alone = root / "alone" / "monday"
    if not (alone / "points.trc").is_file():
        run_stages(videos, alone, options)
    stages = Stages(videos, tmp_path / "ws", options)
    assert stages.register() is None
    tracks = stages.track(tracker=lambda out: shutil.copyfile(alone / "tracks.csv", out))
    assert tracks == tmp_path / "ws" / "tracks.csv"
    registration = stages.subject(tracks)
    assert registration.cameras == tmp_path / "ws" / "register" / "cameras.json"
    stages.solve(registration, tracks)
    stages.record(registration, tracks)
    stages.export(registration)
    assert [s.name for s in stages.result.stages] == [s for s in STAGES if s != "subject"]
    for relative in SAME_BYTES:
        assert (tmp_path / "ws" / relative).read_bytes() == (alone / relative).read_bytes(), relative
    # The same stages again, by a fresh object (another task, another process): everything is up to date.
    again = Stages(videos, tmp_path / "ws", options)
    again.register()
    assert again.finish() == registration
    assert all(s.skipped for s in again.result.stages)


def test_batch_cli_passes_one_rig_calibration_to_every_capture(tmp_path: Path, monkeypatch, capsys) -> None:
    import batch.graph
    from batch.capture import read_capture
    from batch.tasks import job_for
    from dynrecon import cli
    from sfm.options import CalibrationFormat, Units

    capture = simulated_capture(tmp_path / "captures" / "wednesday", SimulatedCaptureOptions(points=2, seconds=0.5))
    rig = tmp_path / "rig.toml"
    (capture / "calibration.toml").rename(rig)  # the rig's one file now serves the capture
    seen = {}

    def fake_run_batch(captures, out, options):  # only the command line's wiring is under test here
        seen["options"] = options.pipeline
        raise SystemExit(0)

    monkeypatch.setattr(batch.graph, "run_batch", fake_run_batch)
    argv = ["batch", str(capture), "--out", str(tmp_path / "season"), "--calibration", str(rig)]
    with pytest.raises(SystemExit):
        cli.main([*argv, "--calibration-format", "toml", "--calibration-units", "m"])
    pipeline = seen["options"]
    assert pipeline.calibration == rig
    assert pipeline.calibration_options.format is CalibrationFormat("toml")
    assert pipeline.calibration_options.units is Units("m")
    assert job_for(read_capture(capture), tmp_path / "season", pipeline).options.calibration == rig

    assert cli.main(["batch", str(capture), "--out", str(tmp_path / "season"), "--calibration", "nope.toml"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.toml" in err[0] and "--calibration" in err[0]
