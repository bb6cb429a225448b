"""DLT coefficient files (DLTdv / easyWand / Argus): cameras we control written in each tool's pixels, read back
through `import-calibration`; the pixel convention told from the cameras' handedness; bad files. The real
DLTdv 7 + easyWand recordings: benchmarks/dltdv_real.py."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from sfm.calibration import DltPixels, read_calibration
from sfm.calibration_dlt import read_dlt_coefficients
from sfm.cameras import read_cameras

from ..dlt_files import coefficients, opencv_to_tool, write_dlt_columns
from .test_import_calibration import _write_video

WIDTH, HEIGHT = 64, 48


def _rig() -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Three cameras 4 m from a right-handed world's origin, looking at it, with skew and fx != fy (a DLT's)."""
    Ks, Rs, ts = [], [], []
    for i, angle in enumerate((0.3, 1.6, 2.9)):
        centre = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.2 + 0.2 * i])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        Ks.append(np.array([[70.0 + 3 * i, 0.4 * i, 31.0 + i], [0.0, 72.0, 22.0 - i], [0.0, 0.0, 1.0]]))
        Rs.append(R)
        ts.append(-R @ centre)
    return Ks, Rs, ts


def _videos(folder: Path, count: int = 3) -> list[Path]:
    videos = []
    for i in range(count):
        videos.append(folder / f"cam{i + 1}.mp4")
        _write_video(videos[-1], 2, (WIDTH, HEIGHT))
    return videos


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = (K @ (X @ R.T + t).T).T
    return x[:, :2] / x[:, 2:]


@pytest.mark.parametrize("pixels", [DltPixels.DLTDV7, DltPixels.DLTDV8, DltPixels.ARGUS])
def test_each_tools_pixels_read_back_exactly(tmp_path: Path, pixels: DltPixels) -> None:
    """The file's cameras project the world as the true cameras do, in OpenCV's pixels; AUTO tells the rows'
    direction from the handedness (Argus by its file name)."""
    Ks, Rs, ts = _rig()
    table = np.stack([coefficients(K, R, t, pixels, HEIGHT) for K, R, t in zip(Ks, Rs, ts, strict=True)])
    name = "wand-dlt-coefficients.csv" if pixels is DltPixels.ARGUS else "wand_dltCoefs.csv"
    path = write_dlt_columns(tmp_path / name, table)
    assert main(["import-calibration", str(path), *map(str, _videos(tmp_path)), "--out", str(tmp_path / "ws")]) == 0
    X = np.random.default_rng(1).normal(0, 0.5, (20, 3))
    for video, K, R, t in zip(read_cameras(tmp_path / "ws" / "cameras.json").videos, Ks, Rs, ts, strict=True):
        frame = video.frames[0]
        assert np.linalg.det(frame.R) == pytest.approx(1.0)
        np.testing.assert_allclose(_project(frame.K, frame.R, frame.t, X), _project(K, R, t, X), atol=1e-6)
        np.testing.assert_allclose(frame.K, K, atol=1e-6)
        np.testing.assert_allclose(frame.R, R, atol=1e-9)
        np.testing.assert_allclose(frame.t, t, atol=1e-9)


def test_a_row_per_camera_and_a_left_handed_world(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A course's .cal (11 numbers a row, OpenCV's pixels) whose world is left-handed: x is negated, and said."""
    Ks, Rs, ts = _rig()
    mirror = np.diag([-1.0, 1.0, 1.0])  # the file's world is ours with x negated
    table = np.stack(
        [coefficients(K, R @ mirror, t, DltPixels.OPENCV, HEIGHT) for K, R, t in zip(Ks, Rs, ts, strict=True)]
    )
    path = tmp_path / "dlt_all_cams.cal"
    path.write_text("\n".join(" ".join(f"{v:.12f}" for v in row) for row in table) + "\n", encoding="utf-8")
    with caplog.at_level(logging.WARNING):
        cameras = read_calibration(path)  # not a DLTdv / Argus name: OpenCV's pixels
    assert "left-handed" in caplog.text and "x negated" in caplog.text
    X = np.random.default_rng(2).normal(0, 0.5, (20, 3))
    for camera, K, R, t in zip(cameras, Ks, Rs, ts, strict=True):
        assert camera.R is not None and camera.t is not None and not camera.cy_plus_height
        # the file's point X is dynrecon's mirror @ X, seen where the file's camera sees X
        np.testing.assert_allclose(
            _project(camera.K, camera.R, camera.t, X @ mirror), _project(K, R @ mirror, t, X), atol=1e-6
        )


def test_millimetres_and_height_free_reading(tmp_path: Path) -> None:
    """A calibration frame in mm (cameras 4,000 units apart) is read in metres; without a video the bottom-up
    principal point row waits for the height."""
    Ks, Rs, ts = _rig()
    table = np.stack(
        [coefficients(K, R, 1000 * t, DltPixels.DLTDV7, HEIGHT) for K, R, t in zip(Ks, Rs, ts, strict=True)]
    )
    path = write_dlt_columns(tmp_path / "frame_dltCoefs.csv", table)
    cameras = read_calibration(path)
    assert [c.name for c in cameras] == ["cam1", "cam2", "cam3"]
    for camera, K, t in zip(cameras, Ks, ts, strict=True):
        assert camera.cy_plus_height and camera.width == camera.height == 0
        np.testing.assert_allclose(camera.t, t, atol=1e-9)
        assert camera.K[1, 2] + HEIGHT == pytest.approx(K[1, 2])


@pytest.mark.parametrize(
    ("text", "what"),
    [
        ("1,2\n" * 8, "2D (planar) DLT"),
        ("1,2,3\n" * 10 + "1,2\n", "line 11"),
        ("1,2,3\n" * 10 + "1,x,3\n", "not a row of numbers"),
        ("1,2,3\n" * 10 + "1,nan,3\n", "NaN or infinite"),
        ("1\n" * 11 * 11, "no DLT file"),
        ((",".join(["1"] * 11) + "\n") * 11, "cannot be told apart"),
        ("", "no DLT coefficients"),
    ],
)
def test_bad_files(tmp_path: Path, text: str, what: str) -> None:
    path = tmp_path / "x_dltCoefs.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match=re.escape(what)):
        read_dlt_coefficients(path)


def test_a_singular_camera(tmp_path: Path) -> None:
    table = np.zeros((2, 11))
    table[0] = coefficients(*[m[0] for m in _rig()], DltPixels.DLTDV7, HEIGHT)
    table[1, [0, 4, 8]] = 1.0  # rows of the 3x3 part all alike
    path = write_dlt_columns(tmp_path / "bad_dltCoefs.csv", table)
    with pytest.raises(InputError, match="camera 2's coefficients describe no camera"):
        read_calibration(path)


def test_cameras_that_disagree_on_the_rows_direction(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    Ks, Rs, ts = _rig()
    table = np.stack(
        [
            coefficients(K, R, t, DltPixels.DLTDV7 if i else DltPixels.DLTDV8, HEIGHT)
            for i, (K, R, t) in enumerate(zip(Ks, Rs, ts, strict=True))
        ]
    )
    path = write_dlt_columns(tmp_path / "mixed_dltCoefs.csv", table)
    assert main(["import-calibration", str(path), *map(str, _videos(tmp_path)), "--out", str(tmp_path / "ws")]) == 2
    error = capsys.readouterr().err
    assert "not of one calibration" in error and error.count("\n") == 1


def _tool_distort(uv: np.ndarray, f: float, c: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The tools' lens model (Bouguet's k1 k2 t1 t2 k3) applied in their own pixels about the profile's centre."""
    x, y = ((uv - c) / f).T
    r2 = x * x + y * y
    radial = 1 + k[0] * r2 + k[1] * r2**2 + k[4] * r2**3
    xd = x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
    yd = y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
    return np.stack([xd, yd], axis=1) * f + c


@pytest.mark.parametrize("pixels", [DltPixels.DLTDV7, DltPixels.DLTDV8])
def test_a_camera_profile_gives_the_lenses(tmp_path: Path, pixels: DltPixels, caplog: pytest.LogCaptureFixture) -> None:
    """easyWand's profile (its distortion in the tool's pixels, y up for DLTdv 7) read with the coefficients: the
    imported cameras put the points where the tool's own lens model does. Without --profile, a profile beside the
    file is pointed out."""
    Ks, Rs, ts = _rig()
    Ks = [np.array([[70.0, 0.0, 31.5], [0.0, 70.0, 23.5], [0.0, 0.0, 1.0]])] * 3  # a profile's pinhole
    table = np.stack([coefficients(K, R, t, pixels, HEIGHT) for K, R, t in zip(Ks, Rs, ts, strict=True)])
    path = write_dlt_columns(tmp_path / "round3_dltCoefs.csv", table)
    lens = np.array([-0.3, 0.11, 0.004, -0.003, 0.0])
    centre = (opencv_to_tool(pixels, HEIGHT) @ [31.5, 23.5, 1.0])[:2]
    profile = tmp_path / "round3_profile.txt"
    rows = [f"{c + 1} 70 {WIDTH} {HEIGHT} {centre[0]} {centre[1]} 1 " + " ".join(map(str, lens)) for c in range(3)]
    profile.write_text("\n".join(rows) + "\n", encoding="utf-8")
    videos = _videos(tmp_path)
    args = ["import-calibration", str(path), *map(str, videos), "--pixels", pixels.value]
    assert main([*args, "--out", str(tmp_path / "ws"), "--profile", str(profile)]) == 0
    X = np.random.default_rng(4).normal(0, 0.5, (30, 3))
    A = opencv_to_tool(pixels, HEIGHT)
    for video, K, R, t in zip(read_cameras(tmp_path / "ws" / "cameras.json").videos, Ks, Rs, ts, strict=True):
        frame = video.frames[0]
        found, _ = cv2.projectPoints(X, cv2.Rodrigues(frame.R)[0], frame.t, frame.K, frame.dist)
        tool = _tool_distort(_project(K, R, t, X) @ A[:2, :2].T + A[:2, 2], 70.0, centre, lens)
        expected = np.linalg.solve(A, np.c_[tool, np.ones(len(tool))].T).T[:, :2]
        np.testing.assert_allclose(found.reshape(-1, 2), expected, atol=1e-6)
    caplog.clear()
    assert main([*args, "--out", str(tmp_path / "plain")]) == 0
    assert "give import-calibration --profile" in caplog.text and "(run: --calibration-profile)" in caplog.text
    caplog.clear()  # once per file: registration reads it in several steps (it was said 8 times in one run)
    assert main([*args, "--out", str(tmp_path / "again")]) == 0
    assert "profile lies beside it" not in caplog.text


@pytest.mark.parametrize("pixels", [DltPixels.DLTDV7, DltPixels.DLTDV8])
def test_easywands_own_mat_file_reads_as_its_exported_coefficients_and_profile(
    tmp_path: Path, pixels: DltPixels, caplog: pytest.LogCaptureFixture
) -> None:
    """easyWand's `*_easyWandData.mat` (the only calibration a real lab's repository held, 2026-11-30): its `coefs`,
    its optimised lenses `nlin` and its image sizes give the cameras that its exported *_dltCoefs.csv and profile
    give, without --size or --profile; a file without the coefficients is a one-line error."""
    import scipy.io

    Ks, Rs, ts = _rig()
    table = np.stack([coefficients(K, R, t, pixels, HEIGHT) for K, R, t in zip(Ks, Rs, ts, strict=True)])
    lens = np.array([[-0.3, 0.11, 0.004, -0.003, 0.0], [-0.2, 0.05, 0.0, 0.001, 0.01], [0.1, 0.0, 0.0, 0.0, 0.0]])
    exported = write_dlt_columns(tmp_path / "wand_dltCoefs.csv", table)
    profile = tmp_path / "wand_profile.txt"
    rows = [f"{c + 1} 70 {WIDTH} {HEIGHT} 31.5 23.5 1 " + " ".join(map(str, lens[c])) for c in range(3)]
    profile.write_text("\n".join(rows) + "\n", encoding="utf-8")
    mat = tmp_path / "wand_easyWandData.mat"
    struct = {
        "coefs": table.T,
        "nlin": lens.ravel(),
        "nlin_est": np.zeros(15),
        "imageWidth": np.full(3, WIDTH, dtype=np.uint16),
        "imageHeight": np.full(3, HEIGHT, dtype=np.uint16),
        "nCams": 3,
    }
    scipy.io.savemat(mat, {"easyWandData": struct})
    from_mat = read_calibration(mat)
    from_csv = read_calibration(exported, profile=profile)
    assert [(c.width, c.height) for c in from_mat] == [(WIDTH, HEIGHT)] * 3
    for a, b in zip(from_mat, from_csv, strict=True):
        K = b.K.copy()
        if b.cy_plus_height:  # the CSV gives no height; the .mat does, so its row is resolved
            K[1, 2] += HEIGHT
        assert not a.cy_plus_height
        np.testing.assert_allclose(a.K, K, atol=1e-9)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)  # the CSV's 12 digits
        np.testing.assert_allclose(a.dist, b.dist, atol=1e-15)
    # a video at half the calibrated size gets the calibrated K scaled, rows counted from the bottom included
    half = tmp_path / "half" / "cam1.mp4"
    half.parent.mkdir()
    _write_video(half, 2, (WIDTH // 2, HEIGHT // 2))
    assert main(["import-calibration", str(mat), str(half), "--out", str(tmp_path / "ws_half")]) == 0
    K_half = read_cameras(tmp_path / "ws_half" / "cameras.json").videos[0].frames[0].K
    K_full = from_csv[0].K.copy()
    if from_csv[0].cy_plus_height:
        K_full[1, 2] += HEIGHT
    np.testing.assert_allclose(K_half[:2, 2], (K_full[:2, 2] + 0.5) / 2 - 0.5, atol=1e-9)
    column = tmp_path / "column_easyWandData.mat"  # a table of a column per camera reads the same
    scipy.io.savemat(column, {"easyWandData": {**struct, "nlin": lens.T}})
    np.testing.assert_allclose([c.dist for c in read_calibration(column)], [c.dist for c in from_mat])
    odd = tmp_path / "odd_easyWandData.mat"  # lenses of the wrong size: said, and none used
    scipy.io.savemat(odd, {"easyWandData": {**struct, "nlin": np.zeros(7), "nlin_est": np.zeros(4)}})
    with caplog.at_level(logging.WARNING):
        assert all(not np.any(c.dist) for c in read_calibration(odd))
    assert "easyWandData.nlin holds 7 values, not 5 per camera of 3" in caplog.text
    renamed = tmp_path / "session.mat"  # told by its variable, whatever its name
    renamed.write_bytes(mat.read_bytes())
    np.testing.assert_allclose(read_calibration(renamed)[1].K, from_mat[1].K)
    scipy.io.savemat(tmp_path / "other_easyWandData.mat", {"easyWandData": {"wandLen": 0.8}})
    with pytest.raises(InputError, match=r"easyWandData\.coefs is missing, not 11 x cameras"):
        read_calibration(tmp_path / "other_easyWandData.mat")
