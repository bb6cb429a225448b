"""The public front of `reconstruct`: solve from objects or paths, write the documented files, import cheaply."""

import subprocess
import sys

import numpy as np
import pytest
from synthetic_motion import smooth_motion

import reconstruct
from reconstruct.stage import run
from sfm.cameras import write_cameras
from simulation.simulate import SimulationOptions, simulate_capture
from tracking.tracks import write_tracks


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("capture")
    capture = simulate_capture(smooth_motion(60, 4), 120.0, SimulationOptions(seed=3))
    write_cameras(folder / "cameras.json", capture.cameras)
    write_tracks(folder / "tracks.csv", capture.tracks)
    return folder, capture


def test_every_public_name_resolves():
    assert set(reconstruct.__all__) == set(reconstruct._HOMES)
    for name in reconstruct.__all__:
        assert getattr(reconstruct, name) is not None
    assert set(reconstruct.__all__) <= set(dir(reconstruct))
    with pytest.raises(AttributeError):
        reconstruct.no_such_name  # noqa: B018


def test_import_is_light():
    code = (
        "import sys, reconstruct; reconstruct.SolveOptions; "
        "print(sorted(m for m in ('rerun', 'pycolmap', 'cv2') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "[]"


def test_solve_write_equals_the_stage(capture, tmp_path):
    folder, simulated = capture
    options = reconstruct.SolveOptions(recording=None)
    result = reconstruct.solve(simulated.cameras, simulated.tracks, options)  # loaded objects
    assert result.points.xyz.shape == (simulated.truth.num_frames, 4, 3)
    assert result.trust.flag.shape == (simulated.truth.num_frames, 4)
    assert result.report["inputs"] == {"cameras": None, "tracks": None}
    result.write(tmp_path / "api")
    run(folder / "cameras.json", folder / "tracks.csv", tmp_path / "stage", options)
    for name in ("points3d.csv", "sequencing.json"):
        assert (tmp_path / "api" / name).read_bytes() == (tmp_path / "stage" / name).read_bytes()
    assert not (tmp_path / "api" / "recording.rrd").exists()
    back = reconstruct.read_points(tmp_path / "api" / "points3d.csv")
    np.testing.assert_allclose(back.xyz, result.points.xyz, rtol=1e-6, atol=1e-6)


def test_paths_are_named_in_the_report(capture):
    folder, _ = capture
    result = reconstruct.solve(
        folder / "cameras.json", str(folder / "tracks.csv"), reconstruct.SolveOptions(recording=None)
    )
    assert result.report["inputs"] == {"cameras": str(folder / "cameras.json"), "tracks": str(folder / "tracks.csv")}
    assert "stage_total" not in result.report["timings"]
