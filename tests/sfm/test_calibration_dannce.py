"""DANNCE / Label3D calibrations: MATLAB's conventions against DANNCE's own projection, both layouts, bad files.
DANNCE's real demo (its labels reproject to 0.00 px): benchmarks/dannce_lab.py."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from dynrecon.cli import main
from dynrecon.errors import InputError
from sfm.calibration import CalibrationFormat, Units, read_calibration
from sfm.cameras import read_cameras

from .test_import_calibration import _rotation, _write_video


def _matlab_camera(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One camera as DANNCE stores it: K' with a 1-based principal point, r = R', t in mm (1, 3)."""
    K = np.array([[900.0 + rng.uniform(0, 100), 0.0, 32.0], [0.0, 905.0, 24.0], [0.0, 0.0, 1.0]])
    R = _rotation(rng)
    t = np.array([0.0, 0.0, 1500.0]) + rng.normal(0, 100, 3)
    return {"K": K.T, "r": R.T, "t": t[None], "RDistort": np.array([[-0.2, 0.1]]), "TDistort": np.array([[1e-3, 0.0]])}


def _dannce_project(X: np.ndarray, cam: dict[str, np.ndarray]) -> np.ndarray:
    """DANNCE's projection (ops.project_to2d, then MATLAB's distortPoints): (N, 3) mm -> (N, 2) MATLAB pixels."""
    M = np.concatenate((cam["r"], cam["t"]), axis=0) @ cam["K"]
    p = np.concatenate((X, np.ones((len(X), 1))), axis=1) @ M
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    K = cam["K"]
    xn, yn = (x - K[2, 0]) / K[0, 0], (y - K[2, 1]) / K[1, 1]
    k1, k2 = cam["RDistort"].ravel()
    p1, p2 = cam["TDistort"].ravel()
    r2 = xn**2 + yn**2
    radial = 1 + k1 * r2 + k2 * r2**2
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn**2)
    yd = yn * radial + p1 * (r2 + 2 * yn**2) + 2 * p2 * xn * yn
    return np.stack([xd * K[0, 0] + K[2, 0], yd * K[1, 1] + K[2, 1]], axis=1)


def _check_projection(found: list, cams: list[dict[str, np.ndarray]]) -> None:
    X = np.random.default_rng(5).normal(0, 40, (30, 3))
    for camera, cam in zip(found, cams, strict=True):
        assert camera.t == pytest.approx(cam["t"].ravel() / 1000)  # mm -> m
        uv, _ = cv2.projectPoints(X / 1000, cv2.Rodrigues(camera.R)[0], camera.t, camera.K, camera.dist)
        # OpenCV's pixels are MATLAB's minus one
        np.testing.assert_allclose(uv.reshape(-1, 2), _dannce_project(X, cam) - 1, atol=1e-6)


def test_a_folder_of_params_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    cams = [_matlab_camera(rng) for _ in range(3)]
    for number, cam in zip((10, 1, 2), cams, strict=True):
        scipy.io.savemat(tmp_path / f"cam{number}_params.mat", cam)
    found = read_calibration(tmp_path)
    assert [c.name for c in found] == ["cam1", "cam2", "cam10"]  # cam2 before cam10
    _check_projection(found, [cams[1], cams[2], cams[0]])
    assert read_calibration(tmp_path, units=Units.M)[0].t == pytest.approx(cams[1]["t"].ravel())


def test_a_label3d_file_imports_by_camera_name(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    cams = [_matlab_camera(rng) for _ in range(2)]
    params = np.empty((2, 1), dtype=object)
    for i, cam in enumerate(cams):
        params[i, 0] = cam
    names = np.empty((1, 2), dtype=object)
    names[0, 0], names[0, 1] = "CameraL", "CameraR"
    path = tmp_path / "rig_dannce.mat"
    scipy.io.savemat(path, {"params": params, "camnames": names})
    _check_projection(read_calibration(path), cams)
    videos = []
    for name in ("CameraR", "CameraL"):  # not the file's order: matched by name
        _write_video(tmp_path / f"{name}.mp4", 3, (64, 48))
        videos.append(str(tmp_path / f"{name}.mp4"))
    assert main(["import-calibration", str(path), *videos, "--out", str(tmp_path / "ws")]) == 0
    result = read_cameras(tmp_path / "ws" / "cameras.json")
    frame = result.videos[0].frames[0]
    assert result.videos[0].name == "CameraR" and frame.t == pytest.approx(cams[1]["t"].ravel() / 1000)
    assert frame.K[0, 2] == pytest.approx(31.0) and len(result.videos[0].frames) == 3


def test_bad_dannce_files_say_what_to_do(tmp_path: Path) -> None:
    cam = _matlab_camera(np.random.default_rng(3))
    one = tmp_path / "cam1_params.mat"
    scipy.io.savemat(one, cam)
    with pytest.raises(InputError, match="one camera's parameters only"):
        read_calibration(one)
    scipy.io.savemat(tmp_path / "other.mat", {"x": np.ones(3)})
    with pytest.raises(InputError, match="no camera parameters"):
        read_calibration(tmp_path / "other.mat")
    for name, content in (
        ("v73.mat", b"MATLAB 7.3 MAT-file" + bytes(200)),
        ("short.mat", b"MATLAB 5.0 MAT-file"),  # truncated
        ("cut.mat", one.read_bytes()[:300]),
        ("noise.mat", np.random.default_rng(0).bytes(2000)),
    ):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(InputError):
            read_calibration(tmp_path / name)
    bad = tmp_path / "bad"
    bad.mkdir()
    scipy.io.savemat(bad / "cam1_params.mat", {**cam, "K": np.ones((2, 2))})
    with pytest.raises(InputError, match="expected"):
        read_calibration(bad, CalibrationFormat.DANNCE)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no DANNCE camera files"):
        read_calibration(empty, CalibrationFormat.DANNCE)


@pytest.mark.parametrize(
    ("change", "message"),
    [({"r": np.ones((3, 3))}, "r is not a rotation"), ({"t": np.array([[0.0, np.nan, 1.0]])}, "not finite")],
)
def test_a_bad_camera_is_named_in_its_own_file(tmp_path: Path, change: dict, message: str) -> None:
    rng = np.random.default_rng(4)
    scipy.io.savemat(tmp_path / "cam1_params.mat", {**_matlab_camera(rng), **change})
    scipy.io.savemat(tmp_path / "cam2_params.mat", _matlab_camera(rng))
    with pytest.raises(InputError, match=message) as error:
        read_calibration(tmp_path, CalibrationFormat.DANNCE)
    assert str(error.value).startswith(f"{tmp_path / 'cam1_params.mat'}:camera 'cam1': ")
