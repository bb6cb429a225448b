"""`dynrecon import-calibration`: TOML round trip against known cameras; the real QCA file's conventions."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from sfm.cameras import FrameCamera, read_cameras
from sfm.import_calibration import StaticCamera, read_qca, write_toml


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _write_video(path: Path, frames: int, size: tuple[int, int], fps: float = 25.0) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    rng = np.random.default_rng(0)
    for _ in range(frames):
        writer.write(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    writer.release()


def test_toml_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    cameras = []
    for i in range(3):
        K = np.array([[500.0 + 10 * i, 0.0, 31.5], [0.0, 505.0, 23.5], [0.0, 0.0, 1.0]])
        cameras.append(
            StaticCamera(
                name=f"cam_{i + 1:02d}",
                width=64,
                height=48,
                K=K,
                dist=np.array([-0.1, 0.02, 0.001, -0.002]),
                R=_rotation(rng),
                t=rng.normal(size=3),
            )
        )
    toml = write_toml(tmp_path / "calib.toml", cameras)
    videos = []
    for i, frames in enumerate((4, 6, 5)):
        path = tmp_path / f"cam{i + 1}.mp4"  # names differ in spelling: cam1 <-> cam_01
        _write_video(path, frames, (64, 48))
        videos.append(str(path))
    assert main(["import-calibration", str(toml), *reversed(videos), "--out", str(tmp_path / "ws")]) == 0
    result = read_cameras(tmp_path / "ws" / "cameras.json")
    assert [v.name for v in result.videos] == ["cam3", "cam2", "cam1"]
    for video, camera, frames in zip(result.videos, reversed(cameras), (5, 6, 4), strict=True):
        assert len(video.frames) == frames
        assert [f.frame for f in video.frames] == list(range(frames))
        np.testing.assert_allclose([f.time for f in video.frames], np.arange(frames) / 25.0, atol=1e-6)
        for frame in video.frames:
            np.testing.assert_allclose(frame.R, camera.R, atol=1e-9)
            np.testing.assert_allclose(frame.t, camera.t, atol=1e-12)
            np.testing.assert_allclose(frame.K, camera.K)
            np.testing.assert_allclose(frame.dist, camera.dist)


def test_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    toml = write_toml(
        tmp_path / "calib.toml",
        [
            StaticCamera(
                name="empty", width=64, height=48, K=np.eye(3), dist=np.zeros(4), R=np.eye(3), t=np.zeros(3)
            )
        ],
    )
    assert main(["import-calibration", str(toml), str(empty), "--out", str(tmp_path / "ws")]) == 2
    assert "empty.mp4: file is empty" in capsys.readouterr().err
    assert main(["import-calibration", str(toml), str(tmp_path), "--out", str(tmp_path / "ws")]) == 2
    assert "is a directory" in capsys.readouterr().err
    video = tmp_path / "other.mp4"
    _write_video(video, 2, (64, 48))
    bad = tmp_path / "bad.toml"
    bad.write_text("[cam_1]\nsize = [64, 48]\nmatrix = [[1, 0], [0, 1]]\n")
    assert main(["import-calibration", str(bad), str(video), "--out", str(tmp_path / "ws")]) == 2
    assert '"matrix" has shape (2, 2)' in capsys.readouterr().err
    assert not (tmp_path / "ws" / "cameras.json").exists()
    with pytest.raises(InputError, match="not valid XML"):
        read_qca(bad)


@pytest.mark.shared
def test_qca_pose2sim(shared_dir: Path, tmp_path: Path) -> None:
    """QCA conventions: each camera looks at the scene centre, upright (image y down = world -z)."""
    demo = shared_dir / "data" / "videos" / "pose2sim_demo"
    qca = demo / "calibration" / "Calib.qca.txt"
    videos = sorted((demo / "videos").glob("cam*.mp4"))
    assert main(["import-calibration", str(qca), *map(str, videos), "--out", str(tmp_path)]) == 0
    cameras = read_cameras(tmp_path / "cameras.json")
    assert [v.name for v in cameras.videos] == ["cam01", "cam02", "cam03", "cam04"]
    centers = np.array([v.frames[0].center for v in cameras.videos])
    np.testing.assert_allclose(centers[0], [1.4602323709, -1.9091590482, 1.8965058524], atol=1e-9)
    target = centers.mean(axis=0) * [1, 1, 0]  # the platform is on the floor between the cameras
    for video, center in zip(cameras.videos, centers, strict=True):
        assert len(video.frames) == 100
        assert len({f.time for f in video.frames}) == 100
        frame = video.frames[0]
        direction = (target - center) / np.linalg.norm(target - center)
        assert frame.R[2] @ direction > 0.97  # optical axis towards the centre
        assert frame.R[1] @ [0, 0, -1] > 0.8  # image "down" is world down
        assert 1670 < frame.K[0, 0] < 1690 and 500 < frame.K[0, 2] < 560 and 940 < frame.K[1, 2] < 970
        # The centre projects near the image middle for every camera: a consistent pose/intrinsics pair.
        uv, _ = cv2.projectPoints(target[None], cv2.Rodrigues(frame.R)[0], frame.t, frame.K, frame.dist)
        assert np.all(np.abs(uv.ravel() - [540, 960]) < [540, 960])


def _epipolar_agreement(
    first: FrameCamera, second: FrameCamera, image_a: np.ndarray, image_b: np.ndarray
) -> int:
    """How many SIFT ratio-test matches between two views lie within 3 px of the poses' epipolar lines."""
    sift = cv2.SIFT_create(8000)
    ka, da = sift.detectAndCompute(cv2.cvtColor(image_a, cv2.COLOR_BGR2GRAY), None)
    kb, db = sift.detectAndCompute(cv2.cvtColor(image_b, cv2.COLOR_BGR2GRAY), None)
    matches = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.8 * n.distance]
    pa = np.array([ka[m.queryIdx].pt for m in matches])[:, None]
    pb = np.array([kb[m.trainIdx].pt for m in matches])[:, None]
    na = cv2.undistortPoints(pa, first.K, first.dist).reshape(-1, 2)
    nb = cv2.undistortPoints(pb, second.K, second.dist).reshape(-1, 2)
    R = second.R @ first.R.T
    t = second.t - R @ first.t
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    lines = np.c_[na, np.ones(len(na))] @ E.T
    distance = np.abs((np.c_[nb, np.ones(len(nb))] * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
    return int((distance * second.K[0, 0] < 3).sum())


@pytest.mark.shared
def test_qca_poses_agree_with_image_matches(shared_dir: Path, tmp_path: Path) -> None:
    """Reprojection consistency between cam01 and cam02 (the pair that shares background): SIFT matches agree
    with the imported poses' epipolar geometry; the transposed-rotation reading of the QCA matrix does not."""
    demo = shared_dir / "data" / "videos" / "pose2sim_demo"
    qca = demo / "calibration" / "Calib.qca.txt"
    videos = [demo / "videos" / "cam01.mp4", demo / "videos" / "cam02.mp4"]
    assert main(["import-calibration", str(qca), *map(str, videos), "--out", str(tmp_path)]) == 0
    cameras = read_cameras(tmp_path / "cameras.json")
    first, second = (v.frames[0] for v in cameras.videos)
    images = [cv2.VideoCapture(str(v)).read()[1] for v in videos]
    agree = _epipolar_agreement(first, second, *images)
    flip = np.diag([1.0, -1.0, -1.0])
    for frame in (first, second):  # the other reading: r_ij transposed, same centre
        center = frame.center
        frame.R = flip @ (flip @ frame.R).T
        frame.t = -frame.R @ center
    wrong = _epipolar_agreement(first, second, *images)
    assert agree >= 8 and agree >= 4 * max(wrong, 1), (agree, wrong)
