"""`dynrecon import-calibration`: TOML round trip against known cameras; the real QCA file's conventions."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from sfm.calibration import StaticCamera, Units, read_calibration, read_qca, read_toml, write_toml
from sfm.calibration import run as import_calibration
from sfm.cameras import FrameCamera, read_cameras, write_cameras
from sfm.intrinsics import known_intrinsics
from sfm.video import probe_video


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


def test_known_clock_offsets(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(4)
    K = np.array([[500.0, 0.0, 31.5], [0.0, 500.0, 23.5], [0.0, 0.0, 1.0]])
    cameras = [
        StaticCamera(name=f"cam{i}", width=64, height=48, K=K, dist=np.zeros(4), R=_rotation(rng), t=rng.normal(size=3))
        for i in (1, 2)
    ]
    toml = write_toml(tmp_path / "calib.toml", cameras)
    videos = []
    for i in (1, 2):
        _write_video(tmp_path / f"cam{i}.mp4", 3, (64, 48))
        videos.append(str(tmp_path / f"cam{i}.mp4"))
    args = ["import-calibration", str(toml), *videos, "--out", str(tmp_path / "ws")]
    assert main([*args, "--offsets", "cam1=0, cam2=-0.04"]) == 0
    capsys.readouterr()
    assert [v.clock_offset for v in read_cameras(tmp_path / "ws" / "cameras.json").videos] == [0.0, -0.04]
    # milliseconds typed for seconds: the two videos' 0.08 s would share no time, and a solve would fit each alone
    assert main([*args, "--offsets", "cam1=0,cam2=33"]) == 2
    err = capsys.readouterr().err
    assert "--offsets cam2=33 puts its 0.08 s at 33-33.08 s, sharing no time with cam1 (0-0.08 s)" in err
    assert "33 ms is 0.033" in err
    assert main([*args, "--offsets", "cam2=0.5"]) == 0  # a video left out gets none
    assert [v.clock_offset for v in read_cameras(tmp_path / "ws" / "cameras.json").videos] == [None, 0.5]
    assert [v.clock_declared for v in read_cameras(tmp_path / "ws" / "cameras.json").videos] == [False, True]
    assert main([*args, "--synchronized"]) == 0
    assert [v.clock_offset for v in read_cameras(tmp_path / "ws" / "cameras.json").videos] == [0.0, 0.0]
    assert all(v.clock_declared for v in read_cameras(tmp_path / "ws" / "cameras.json").videos)
    document = json.loads((tmp_path / "ws" / "cameras.json").read_text())
    document["videos"][0]["clock_declared"] = "yes"
    (tmp_path / "ws" / "cameras.json").write_text(json.dumps(document))
    with pytest.raises(InputError, match='"clock_declared" must be true or false'):
        read_cameras(tmp_path / "ws" / "cameras.json")
    document["videos"][0]["clock_declared"] = True
    del document["videos"][0]["clock_offset"]
    (tmp_path / "ws" / "cameras.json").write_text(json.dumps(document))
    with pytest.raises(InputError, match='"clock_declared" is true but there is no "clock_offset"'):
        read_cameras(tmp_path / "ws" / "cameras.json")
    capsys.readouterr()
    assert main([*args, "--offsets", "cam3=0.1"]) == 2
    assert "--offsets names video 'cam3', which is not among the videos (cam1, cam2)" in capsys.readouterr().err
    for wrong in ("cam1=soon", "cam1=0,cam1=1", "cam1=nan", "0.5"):
        with pytest.raises(SystemExit) as exit_:  # argparse's usage line and one error line
            main([*args, "--offsets", wrong])
        assert exit_.value.code == 2
        assert "give NAME=SECONDS once per video" in capsys.readouterr().err
    assert main([*args, "--offsets", "cam1=0", "--synchronized"]) == 2
    assert "--synchronized and --offsets both given" in capsys.readouterr().err


def test_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    toml = write_toml(
        tmp_path / "calib.toml",
        [StaticCamera(name="empty", width=64, height=48, K=np.eye(3), dist=np.zeros(4), R=np.eye(3), t=np.zeros(3))],
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


def _epipolar_agreement(first: FrameCamera, second: FrameCamera, image_a: np.ndarray, image_b: np.ndarray) -> int:
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


# ----------------------------------------------------------------------------------------------------------
# caliscope and FreeMoCap layouts


def _row(values: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(v)) for v in np.ravel(values)) + "]"


def _matrix(values: np.ndarray) -> str:
    return "[" + ", ".join(_row(r) for r in values) + "]"


def _write_caliscope(path: Path, cameras: list[StaticCamera], *, config: bool = False, ignore: int = -1) -> Path:
    """caliscope's camera_array.toml ([cameras.N]) or config.toml ([cam_N] plus [charuco]); rotation a matrix."""
    lines = []
    for index, camera in enumerate(cameras):
        lines += [
            f"[cam_{index}]" if config else f"[cameras.{index}]",
            f"cam_id = {index}",
            "rotation_count = 0",
            f"ignore = {'true' if index == ignore else 'false'}",
            f"size = [{camera.width}, {camera.height}]",
            f"matrix = {_matrix(camera.K)}",
            f"distortions = {_row(camera.dist)}",
        ]
        if camera.R is not None and camera.t is not None:
            lines += [f"translation = {_row(camera.t)}", f"rotation = {_matrix(camera.R)}"]
        lines.append("")
    if config:
        lines += ["[charuco]", "columns = 4", "rows = 5", 'dictionary = "DICT_4X4_1000"', ""]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _write_freemocap(path: Path, cameras: list[StaticCamera]) -> Path:
    """FreeMoCap's *_camera_calibration.toml: anipose's [cam_N], Rodrigues rotation, translation in mm."""
    lines = []
    for index, camera in enumerate(cameras):
        assert camera.R is not None and camera.t is not None
        lines += [
            f"[cam_{index}]",
            f'name = "{camera.name}"',
            f"size = [{camera.width}, {camera.height}]",
            f"matrix = {_matrix(camera.K)}",
            f"distortions = {_row(camera.dist)}",
            f"rotation = {_row(cv2.Rodrigues(camera.R)[0])}",
            f"translation = {_row(camera.t * 1000.0)}",
            "",
        ]
    lines += [
        "[metadata]",
        "charuco_square_size = 39",
        'charuco_board_object = "CharucoBoardDefinition(7x5)"',
        'path_to_recorded_videos = "/recording/synchronized_videos"',
        'date_time_calibrated = "2024-01-01T00:00:00"',
        "",
    ]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _random_cameras(names: list[str], seed: int = 5) -> list[StaticCamera]:
    rng = np.random.default_rng(seed)
    return [
        StaticCamera(
            name=name,
            width=64,
            height=48,
            K=np.array([[500.0 + 7 * i, 0.0, 31.5], [0.0, 502.0, 23.5], [0.0, 0.0, 1.0]]),
            dist=np.array([-0.1 * i, 0.02, 0.001, -0.002, 0.003]),
            R=_rotation(rng),
            t=rng.normal(size=3),
        )
        for i, name in enumerate(names)
    ]


def _assert_same(read: list[StaticCamera], cameras: list[StaticCamera]) -> None:
    assert [c.name for c in read] == [c.name for c in cameras]
    for got, want in zip(read, cameras, strict=True):
        assert (got.width, got.height) == (want.width, want.height)
        np.testing.assert_allclose(got.K, want.K)
        np.testing.assert_allclose(got.dist, want.dist)
        assert got.R is not None and want.R is not None and got.t is not None and want.t is not None
        np.testing.assert_allclose(got.R, want.R, atol=1e-12)
        np.testing.assert_allclose(got.t, want.t, atol=1e-12)


@pytest.mark.parametrize("config", [False, True], ids=["camera_array", "config"])
def test_caliscope_round_trip(tmp_path: Path, config: bool) -> None:
    cameras = _random_cameras(["cam_0", "cam_1", "cam_2"])
    path = _write_caliscope(tmp_path / "layout.toml", cameras, config=config, ignore=1)
    _assert_same(read_calibration(path), [cameras[0], cameras[2]])  # cam_1 has ignore = true


def test_an_older_caliscope_sessions_port_videos_find_their_cameras(tmp_path: Path) -> None:
    """caliscope's older sessions write [cam_N] with `port = N` and record port_N.mp4: each video takes the camera
    of its port, also where the file has more cameras than the session has videos."""
    cameras = _random_cameras(["cam_0", "cam_1", "cam_2"])
    text = _write_caliscope(tmp_path / "config.toml", cameras, config=True).read_text(encoding="utf-8")
    # ports in another order than the tables: the port decides, not the position
    for index, port in enumerate((2, 0, 1)):
        text = text.replace(f"cam_id = {index}\n", f"port = {port}\n", 1)
    (tmp_path / "config.toml").write_text(text, encoding="utf-8")
    videos = []
    for port in (1, 2):
        _write_video(tmp_path / f"port_{port}.mp4", 5, (64, 48))
        videos.append(str(tmp_path / f"port_{port}.mp4"))
    assert main(["import-calibration", str(tmp_path / "config.toml"), *videos, "--out", str(tmp_path / "ws")]) == 0
    written = read_cameras(tmp_path / "ws" / "cameras.json")
    # port 1 is the third table's camera (cam_2), port 2 the first's (cam_0)
    for video, table in zip(written.videos, (2, 0), strict=True):
        np.testing.assert_allclose(video.frames[0].K, cameras[table].K)


def test_freemocap_round_trip_millimetres(tmp_path: Path) -> None:
    """FreeMoCap: camera names are the video stems; [metadata] charuco_square_size means mm translations."""
    cameras = _random_cameras(["Camera_000_synchronized", "Camera_001_synchronized"])
    path = _write_freemocap(tmp_path / "recording_camera_calibration.toml", cameras)
    _assert_same(read_calibration(path), cameras)
    as_metres = read_toml(path, Units.M)  # forced: the translations are read as they are written
    np.testing.assert_allclose(as_metres[1].t, 1000.0 * cameras[1].t)
    videos = []
    for camera in cameras:
        videos.append(tmp_path / f"{camera.name}.mp4")
        _write_video(videos[-1], 3, (64, 48))
    assert main(["import-calibration", str(path), *map(str, videos), "--out", str(tmp_path / "ws")]) == 0
    result = read_cameras(tmp_path / "ws" / "cameras.json")
    np.testing.assert_allclose(result.videos[1].frames[0].t, cameras[1].t, atol=1e-12)
    assert main(["import-calibration", str(path), *map(str, videos), "--out", str(tmp_path / "m"), "--units", "m"]) == 0
    result = read_cameras(tmp_path / "m" / "cameras.json")
    np.testing.assert_allclose(result.videos[1].frames[0].t, 1000.0 * cameras[1].t, atol=1e-9)


def test_anipose_millimetres(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """sleap-anipose writes its board (square_length, mm) into [metadata]: mm translations. anipose's own files
    give no unit: cameras hundreds of units apart are read in mm, with a warning; a metric lab is left in metres."""
    cameras = _random_cameras(["back", "top"])
    for camera in cameras:
        camera.t = camera.t * 300.0  # a rig about 0.5 m across, written in mm
    path = write_toml(tmp_path / "calibration.toml", cameras)
    text = path.read_text(encoding="utf-8").replace("adjusted = false", "board_x = 8\nsquare_length = 24.0")
    path.write_text(text, encoding="utf-8")
    np.testing.assert_allclose(read_calibration(path)[1].t, cameras[1].t / 1000.0)
    write_toml(path, cameras)  # anipose's own [metadata]: no unit given
    with caplog.at_level("WARNING"):
        read = read_calibration(path)
    np.testing.assert_allclose(read[1].t, cameras[1].t / 1000.0)
    assert "translations read in millimetres (--units m if they are metres)" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        read_calibration(path)  # registration reads the file in several steps: said once
    assert "translations read in" not in caplog.text
    np.testing.assert_allclose(read_calibration(path, units=Units.M)[1].t, cameras[1].t)
    text = path.read_text(encoding="utf-8").replace("adjusted = false", "square_length = 0.024")
    path.write_text(text, encoding="utf-8")  # a board in metres: the translations too
    np.testing.assert_allclose(read_calibration(path)[1].t, cameras[1].t / 1000.0)  # still > 100 apart: mm
    middling = _random_cameras(["cam_1", "cam_2"])
    for camera in middling:
        camera.t = camera.t * 20.0
    caplog.clear()
    with caplog.at_level("WARNING"):
        np.testing.assert_allclose(read_calibration(write_toml(path, middling))[1].t, middling[1].t)
    assert "read in metres (--units mm if they are millimetres)" in caplog.text
    metric = _random_cameras(["cam_1", "cam_2"])  # about 2 units apart: metres, no warning
    caplog.clear()
    with caplog.at_level("WARNING"):
        np.testing.assert_allclose(read_calibration(write_toml(path, metric))[1].t, metric[1].t)
    assert "millimetres" not in caplog.text


def test_rotation_matrix_or_rodrigues_in_every_layout(tmp_path: Path) -> None:
    R = _rotation(np.random.default_rng(11))
    rvec = cv2.Rodrigues(R)[0].ravel()
    common = "size = [64, 48]\nmatrix = [[500.0, 0.0, 32.0], [0.0, 500.0, 24.0], [0.0, 0.0, 1.0]]\n"
    common += "translation = [0.1, 0.2, 0.3]\n"
    for header in ("[cam_1]", "[cameras.0]\ncam_id = 0"):
        for rotation in (_row(rvec), _matrix(R), _row(R)):  # Rodrigues, nested 3x3, 9 flat numbers
            path = tmp_path / "r.toml"
            path.write_text(f"{header}\n{common}rotation = {rotation}\n", encoding="utf-8")
            (camera,) = read_calibration(path)
            np.testing.assert_allclose(camera.R, R, atol=1e-12)
    path.write_text(f"[cam_1]\n{common}rotation = {_matrix(2 * R)}\n", encoding="utf-8")
    with pytest.raises(InputError, match="not a rotation"):
        read_calibration(path)
    path.write_text(f"[cam_1]\n{common}rotation = [1.0, 2.0]\n", encoding="utf-8")
    with pytest.raises(InputError, match="expected a Rodrigues vector"):
        read_calibration(path)


def test_intrinsics_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """caliscope before the capture-volume step: intrinsics for `register --intrinsics`, no import-calibration."""
    cameras = _random_cameras(["cam_0", "cam_1"])
    for camera in cameras:
        camera.R = camera.t = None
    path = _write_caliscope(tmp_path / "camera_array.toml", cameras)
    with open(path, "a", encoding="utf-8") as handle:  # a camera not calibrated at all is skipped
        handle.write("[cameras.2]\ncam_id = 2\nsize = [64, 48]\nignore = false\n")
    read = read_calibration(path)
    assert [c.name for c in read] == ["cam_0", "cam_1"] and not any(c.has_pose for c in read)
    videos = [tmp_path / "cam_1.mp4", tmp_path / "cam_0.mp4"]
    for video in videos:
        _write_video(video, 2, (64, 48))
    intrinsics = known_intrinsics(path, [probe_video(v) for v in videos])
    np.testing.assert_allclose(intrinsics["cam_1"][0], cameras[1].K)
    np.testing.assert_allclose(intrinsics["cam_0"][1], cameras[0].dist)
    assert main(["import-calibration", str(path), *map(str, videos), "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err
    assert "camera 'cam_1' has intrinsics only" in err, err
    assert not (tmp_path / "ws" / "cameras.json").exists()


# Written down from ../shared/data/videos/caliscope_office/camera_array.toml (config.toml holds the same cameras):
# K, distortions of cam_0 and cam_3, and every centre -R^T t (metres).
CALISCOPE_K0 = [[903.550124089999, 0.0, 618.3086297620227], [0.0, 907.8788668762852, 394.213230569746], [0, 0, 1]]
CALISCOPE_DIST3 = [
    0.16889026717338923,
    -0.22656481380801907,
    0.0014291725779222067,
    0.00041512649462704715,
    0.10610964089301607,
]
CALISCOPE_CENTERS = [
    [-0.6521290816, -0.2411164052, -0.1469386797],
    [-0.3501496933, 0.8444593255, -0.0408395456],
    [-0.5749959796, 0.0322955931, 0.3235560651],
    [-0.5736973443, -0.5612476560, 0.1233698960],
]


@pytest.mark.shared
@pytest.mark.parametrize("name", ["camera_array.toml", "config.toml"])
def test_caliscope_real_files(shared_dir: Path, name: str) -> None:
    cameras = read_calibration(shared_dir / "data" / "videos" / "caliscope_office" / name)
    assert [c.name for c in cameras] == ["cam_0", "cam_1", "cam_2", "cam_3"]
    assert all((c.width, c.height) == (1280, 720) for c in cameras)
    np.testing.assert_allclose(cameras[0].K, CALISCOPE_K0, rtol=1e-15)
    np.testing.assert_allclose(cameras[3].dist, CALISCOPE_DIST3, rtol=1e-15)
    np.testing.assert_allclose([c.center for c in cameras], CALISCOPE_CENTERS, atol=2e-10)
    np.testing.assert_allclose(cameras[1].t, [0.30872148305699454, -0.14760639347661925, 0.8486976063733689])


@pytest.mark.shared
def test_import_caliscope_videos(shared_dir: Path, tmp_path: Path) -> None:
    office = shared_dir / "data" / "videos" / "caliscope_office"
    videos = [office / "calibration" / "extrinsic" / f"cam_{i}.mp4" for i in (2, 0, 3, 1)]
    assert (
        main(["import-calibration", str(office / "camera_array.toml"), *map(str, videos), "--out", str(tmp_path)]) == 0
    )
    result = read_cameras(tmp_path / "cameras.json")
    assert [v.name for v in result.videos] == ["cam_2", "cam_0", "cam_3", "cam_1"]
    for video, i in zip(result.videos, (2, 0, 3, 1), strict=True):
        assert (video.width, video.height) == (1280, 720) and len(video.frames) == 111
        centers = np.array([f.center for f in video.frames])
        np.testing.assert_allclose(centers, np.broadcast_to(CALISCOPE_CENTERS[i], centers.shape), atol=1e-9)


def test_a_video_resized_from_the_calibrated_size_gets_scaled_intrinsics(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    K = np.array([[200.0, 0.0, 61.0], [0.0, 202.0, 45.5], [0.0, 0.0, 1.0]])
    camera = StaticCamera(name="cam_1", width=128, height=96, K=K, dist=np.zeros(4), R=np.eye(3), t=np.zeros(3))
    toml = write_toml(tmp_path / "calib.toml", [camera])
    half, other = tmp_path / "half" / "cam1.mp4", tmp_path / "other" / "cam1.mp4"
    foreign = tmp_path / "foreign" / "cam1.mp4"
    for path, size in ((half, (64, 48)), (other, (112, 96)), (foreign, (64, 40))):
        path.parent.mkdir()
        _write_video(path, 3, size)

    # Ground truth: a point's pixel in the calibrated image, carried into the half-size image by the resize
    # (OpenCV's pixel centres: x' = (x + 0.5) / 2 - 0.5).
    X = np.array([0.3, -0.2, 2.0])
    full = (K @ X)[:2] / X[2]
    scaled, _ = known_intrinsics(toml, [probe_video(half)])["cam1"]
    np.testing.assert_allclose((scaled @ X)[:2] / X[2], (full + 0.5) / 2 - 0.5, atol=1e-9)
    assert main(["import-calibration", str(toml), str(half), "--out", str(tmp_path / "ws")]) == 0
    np.testing.assert_allclose(read_cameras(tmp_path / "ws" / "cameras.json").videos[0].frames[0].K, scaled)

    # another aspect ratio (a crop or a padding): unchanged, and said
    with caplog.at_level("WARNING"):
        kept, _ = known_intrinsics(toml, [probe_video(other)])["cam1"]
    np.testing.assert_array_equal(kept, K)
    assert "another aspect ratio" in caplog.text and "cam1.mp4 is 112x96" in caplog.text

    # another aspect ratio with the principal point outside the video: not the calibrated image; estimated instead
    with caplog.at_level("WARNING"):
        assert "cam1" not in known_intrinsics(toml, [probe_video(foreign)])
    assert "lies outside this video" in caplog.text


def test_a_principal_point_outside_its_own_calibrated_image_is_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """cx = -1 at the calibrated size (a typo or another camera's table: a mutation sweep, 2026-11-30) was used
    without a word; a file without sizes was already warned about."""
    K = np.array([[200.0, 0.0, -1.0], [0.0, 202.0, 45.5], [0.0, 0.0, 1.0]])
    camera = StaticCamera(name="cam_1", width=128, height=96, K=K, dist=np.zeros(4), R=np.eye(3), t=np.zeros(3))
    toml = write_toml(tmp_path / "calib.toml", [camera])
    video = tmp_path / "cam1.mp4"
    _write_video(video, 3, (128, 96))
    with caplog.at_level("WARNING"):
        assert main(["import-calibration", str(toml), str(video), "--out", str(tmp_path / "ws")]) == 0
    assert "camera cam_1: principal point (-1.0, 45.5) outside this 128x96 video" in caplog.text
    np.testing.assert_array_equal(read_cameras(tmp_path / "ws" / "cameras.json").videos[0].frames[0].K, K)


def test_opencvs_rational_lens_model_is_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Eight distortion coefficients (OpenCV's CALIB_RATIONAL_MODEL; multiview_calib's drone rig) were refused; they
    go into cameras.json as they are. Six are no OpenCV model: refused, saying what to do."""
    K = np.array([[200.0, 0.0, 63.5], [0.0, 202.0, 47.5], [0.0, 0.0, 1.0]])
    rational = np.array([0.9, 0.2, 0.001, -0.002, 0.01, 1.1, 0.3, 0.02])
    camera = StaticCamera(name="cam_1", width=128, height=96, K=K, dist=rational, R=np.eye(3), t=np.zeros(3))
    toml = write_toml(tmp_path / "calib.toml", [camera])
    video = tmp_path / "cam1.mp4"
    _write_video(video, 3, (128, 96))
    assert main(["import-calibration", str(toml), str(video), "--out", str(tmp_path / "ws")]) == 0
    np.testing.assert_allclose(read_cameras(tmp_path / "ws" / "cameras.json").videos[0].frames[0].dist, rational)
    toml.write_text(toml.read_text().replace("0.02,", "").replace("0.3,", ""))  # six coefficients left
    assert main(["import-calibration", str(toml), str(video), "--out", str(tmp_path / "ws6")]) == 2
    err = capsys.readouterr().err
    assert '"distortions" has 6 values, expected 4, 5 or 8' in err and "undistort the tracks first" in err


def test_intrinsics_alone_make_no_guess_about_units(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """--intrinsics takes no translation, so the unit guess of a rig 50 units across (and its warning: a real lab's
    calibration, 2026-11-30) has no place there; import-calibration still says it."""
    K = np.array([[200.0, 0.0, 63.5], [0.0, 202.0, 47.5], [0.0, 0.0, 1.0]])
    cameras = [
        StaticCamera(name=f"cam_{i}", width=128, height=96, K=K, dist=np.zeros(4), R=np.eye(3), t=np.array(t))
        for i, t in ((1, [0.0, 0.0, 1.0]), (2, [50.0, 0.0, 1.0]))
    ]
    toml = write_toml(tmp_path / "calib.toml", cameras)
    videos = []
    for i in (1, 2):
        _write_video(tmp_path / f"cam{i}.mp4", 3, (128, 96))
        videos.append(probe_video(tmp_path / f"cam{i}.mp4"))
    with caplog.at_level("WARNING"):
        assert set(known_intrinsics(toml, videos)) == {"cam1", "cam2"}
    assert "units apart" not in caplog.text
    with caplog.at_level("WARNING"):
        read_calibration(toml)
    assert "the cameras are up to 50 units apart" in caplog.text


def test_a_video_turned_from_the_calibrated_image(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A portrait video of a camera calibrated in landscape (or the reverse): `register --intrinsics` estimates
    that video's intrinsics instead of using a K that does not fit it, and `import-calibration`, whose poses would
    be wrong too, refuses it in one line."""
    K = np.array([[200.0, 0.0, 61.0], [0.0, 202.0, 45.5], [0.0, 0.0, 1.0]])
    camera = StaticCamera(name="cam_1", width=128, height=96, K=K, dist=np.zeros(4), R=np.eye(3), t=np.zeros(3))
    toml = write_toml(tmp_path / "calib.toml", [camera])
    turned = tmp_path / "turned" / "cam1.mp4"
    turned.parent.mkdir()
    _write_video(turned, 3, (48, 64))  # portrait, half size
    with caplog.at_level("WARNING"):
        assert known_intrinsics(toml, [probe_video(turned)]) == {}
    assert "turned by 90 degrees" in caplog.text and "estimated from the data instead" in caplog.text
    with pytest.raises(InputError, match="turned by 90 degrees"):
        import_calibration(toml, [turned], tmp_path / "ws")


def test_cameras_json_of_another_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A board recording's cameras.json calibrates the session's videos of the same static cameras: their poses,
    K and distortion carried over by name (another frame count, `cam01` <-> `cam_1`); `--intrinsics` takes its K;
    a camera that moves in that recording has no one pose to give."""
    rng = np.random.default_rng(5)
    cameras = _random_cameras(["cam_1", "cam_2"])
    board = tmp_path / "board"
    videos = []
    for camera in cameras:
        path = board / f"{camera.name}.mp4"
        path.parent.mkdir(exist_ok=True)
        _write_video(path, 3, (camera.width, camera.height))
        videos.append(str(path))
    toml = write_toml(tmp_path / "calib.toml", cameras)
    assert main(["import-calibration", str(toml), *videos, "--out", str(board)]) == 0
    session = []
    for name in ("cam01", "cam02"):
        path = tmp_path / "session" / f"{name}.mp4"
        path.parent.mkdir(exist_ok=True)
        _write_video(path, 7, (64, 48))
        session.append(str(path))
    assert main(["import-calibration", str(board / "cameras.json"), *session, "--out", str(tmp_path / "ws")]) == 0
    result = read_cameras(tmp_path / "ws" / "cameras.json")
    assert [v.name for v in result.videos] == ["cam01", "cam02"] and all(len(v.frames) == 7 for v in result.videos)
    assert all(v.clock_offset is None for v in result.videos)  # no clock known: the solve finds the offsets
    synced = ["import-calibration", str(board / "cameras.json"), *session, "--out", str(tmp_path / "synced")]
    assert main([*synced, "--synchronized"]) == 0  # a triggered rig: one clock, which the solve then tests
    assert [v.clock_offset for v in read_cameras(tmp_path / "synced" / "cameras.json").videos] == [0.0, 0.0]
    for video, camera in zip(result.videos, cameras, strict=True):
        np.testing.assert_allclose(video.frames[6].R, camera.R, atol=1e-9)
        np.testing.assert_allclose(video.frames[6].t, camera.t, atol=1e-12)
        np.testing.assert_allclose(video.frames[6].K, camera.K)
        np.testing.assert_allclose(video.frames[6].dist, camera.dist)
    intrinsics = known_intrinsics(board / "cameras.json", [probe_video(Path(v)) for v in session])
    np.testing.assert_allclose(intrinsics["cam02"][0], cameras[1].K)

    moved = read_cameras(board / "cameras.json")
    moved.videos[1].frames[2].t = moved.videos[1].frames[2].t + rng.normal(size=3)
    write_cameras(board / "cameras.json", moved)
    assert main(["import-calibration", str(board / "cameras.json"), *session, "--out", str(tmp_path / "ws2")]) == 2
    err = capsys.readouterr().err
    assert "video 'cam_2''s camera moves in this recording" in err and "leave that camera's video out" in err, err
    assert not (tmp_path / "ws2" / "cameras.json").exists()


def test_a_camera_given_twice_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """sleap-anipose's test calibration gives its `side` camera `top`'s table: two videos at one pose would be
    triangulated from a zero baseline. import-calibration refuses it, naming both; --intrinsics takes the K."""
    cameras = _random_cameras(["side", "top"])
    cameras[1].R, cameras[1].t = cameras[0].R, cameras[0].t
    toml = write_toml(tmp_path / "calibration.toml", cameras)
    videos = []
    for camera in cameras:
        videos.append(tmp_path / f"{camera.name}.mp4")
        _write_video(videos[-1], 2, (64, 48))
    assert main(["import-calibration", str(toml), *map(str, videos), "--out", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "cameras 'side' and 'top' have the same pose: one camera given twice" in err, err
    assert not (tmp_path / "ws" / "cameras.json").exists()
    np.testing.assert_allclose(known_intrinsics(toml, [probe_video(v) for v in videos])["top"][0], cameras[1].K)


def test_a_turned_video_of_a_letterboxed_calibration_is_seen_as_turned() -> None:
    """Pose2Sim's cam01 video is 1080x1920 of a 1088x1920 calibration (letterboxed by 0.74 %); turned by its
    rotation flag it is 1920x1080, which is the calibrated image turned, not a crop to keep K for."""
    from sfm.calibration import TurnedVideoError, intrinsics_at_video_size
    from sfm.video import ProbedVideo

    K = np.array([[1681.2, 0.0, 533.0], [0.0, 1681.1, 948.1], [0.0, 0.0, 1.0]])
    turned = ProbedVideo(
        path=Path("cam01.mp4"), name="cam01", width=1920, height=1080, times=np.arange(5) / 60, nominal_fps=60.0
    )
    with pytest.raises(TurnedVideoError, match="turned by 90 degrees"):
        intrinsics_at_video_size(K, (1088, 1920), turned, "cam01")
    upright = ProbedVideo(
        path=Path("cam01.mp4"), name="cam01", width=1080, height=1920, times=np.arange(5) / 60, nominal_fps=60.0
    )
    np.testing.assert_array_equal(intrinsics_at_video_size(K, (1088, 1920), upright, "cam01"), K)


def test_a_session_prefix_or_take_suffix_around_the_camera_name_matches(tmp_path: Path) -> None:
    """sleap-anipose's videos are minimal_back.mp4 ... for cameras back, mid, side, top; three of the four videos
    given (side's table is a copy): each matched to its camera by the name it ends with, side left out."""
    cameras = _random_cameras(["back", "mid", "side", "top"])
    toml = write_toml(tmp_path / "calibration.toml", cameras)
    videos = []
    for name in ("minimal_top", "minimal_back", "mid_take2"):
        videos.append(tmp_path / f"{name}.mp4")
        _write_video(videos[-1], 2, (64, 48))
    assert main(["import-calibration", str(toml), *map(str, videos), "--out", str(tmp_path / "ws")]) == 0
    got = read_cameras(tmp_path / "ws" / "cameras.json").videos
    for video, camera in zip(got, (cameras[3], cameras[0], cameras[1]), strict=True):
        np.testing.assert_allclose(video.frames[0].R, camera.R, atol=1e-9)


def test_within_name_wants_one_whole_run_of_words() -> None:
    from dynrecon.names import within_name

    assert within_name("minimal_back", ["back", "mid"]) == ["back"]
    assert within_name("cam01_take2", ["cam_1", "cam_11"]) == ["cam_1"]
    assert within_name("trial_cam11", ["cam_1", "cam_11"]) == ["cam_11"]
    assert within_name("cam1_take2", ["1", "2"]) == []  # numbers alone: a take's number is no camera's
    assert within_name("background", ["back"]) == []  # words, not letters
    assert within_name("back", ["back"]) == []  # the same name is spelled_alike's


def test_holds_name_finds_a_camera_named_around_the_video() -> None:
    """Pose2Sim's Calib_scene.toml names its cameras int_cam01_img ...: cam01.mp4 is camera int_cam01_img."""
    from dynrecon.names import holds_name

    cameras = ["int_cam01_img", "int_cam02_img", "int_cam11_img"]
    assert holds_name("cam01", cameras) == ["int_cam01_img"] and holds_name("cam_2", cameras) == ["int_cam02_img"]
    assert holds_name("cam1", ["int_cam1_img", "ext_cam1_img"]) == ["int_cam1_img", "ext_cam1_img"]  # ambiguous
    assert holds_name("01", cameras) == []  # numbers alone name no camera
    assert holds_name("cam", cameras) == ["int_cam01_img", "int_cam02_img", "int_cam11_img"]
    assert holds_name("int_cam01_img", cameras) == []  # the same name is spelled_alike's


def test_import_calibration_never_writes_over_the_file_it_reads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`import-calibration WS/cameras.json VIDEO... --out WS` would write the cameras.json it reads, dropping what
    the import does not carry (its clock offsets): a one-line refusal, the file untouched."""
    from dynrecon.cli import main

    cameras = tmp_path / "cameras.json"
    cameras.write_text('{"videos": []}', encoding="utf-8")
    video = tmp_path / "cam_0.mp4"
    video.write_bytes(b"")
    assert main(["import-calibration", str(cameras), str(video), "--out", str(tmp_path)]) == 2
    assert "is the cameras.json this import would write" in capsys.readouterr().err
    assert cameras.read_text(encoding="utf-8") == '{"videos": []}'


def test_cameras_named_around_the_videos_match_only_all_of_them() -> None:
    """Pose2Sim's int_cam01_img ... match cam01 ... by name; where only some videos' names lie inside camera
    names (left, right against cam_left, cam_2), the order decides as before, not an error."""
    from sfm.calibration import match_cameras
    from sfm.video import ProbedVideo

    def videos(*names: str) -> list[ProbedVideo]:
        return [
            ProbedVideo(path=Path(f"{n}.mp4"), name=n, width=64, height=48, times=np.arange(3) / 30, nominal_fps=30.0)
            for n in names
        ]

    cameras = _random_cameras(["int_cam02_img", "int_cam01_img"])
    assert [c.name for c in match_cameras(cameras, videos("cam01", "cam02"), Path("c.toml"))] == [
        "int_cam01_img",
        "int_cam02_img",
    ]
    cameras = _random_cameras(["cam_left", "cam_2"])
    assert [c.name for c in match_cameras(cameras, videos("left", "right"), Path("c.toml"))] == ["cam_left", "cam_2"]
    # anipose names its cameras by number ('10' ... '21'): videos cam10 ... match them, some cameras unused
    cameras = _random_cameras(["10", "11", "12"])
    assert [c.name for c in match_cameras(cameras, videos("cam12", "cam10"), Path("c.toml"))] == ["12", "10"]


def test_numbered_name_is_one_word_and_the_camera_number() -> None:
    from dynrecon.names import numbered_name

    assert numbered_name("cam10", ["10", "11"]) == ["10"] and numbered_name("Camera_07", ["7", "07x"]) == ["7"]
    assert numbered_name("cam1_take2", ["1", "2"]) == []  # a take's number is no camera's
    assert numbered_name("10", ["10"]) == [] and numbered_name("cam10", ["cam10"]) == []


@pytest.mark.parametrize("command", ["import-calibration", "register"])
def test_a_broken_calibration_file_is_said_before_the_videos_are_probed(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A typo in the calibration (or --intrinsics) file was said only after every video was probed (seconds each,
    minutes for long videos): the file is read first."""
    import sfm.calibration
    import sfm.stage

    def no_probe(*args: object, **kwargs: object) -> None:
        raise AssertionError("a video was probed before the calibration file was read")

    monkeypatch.setattr(sfm.calibration, "probe_video", no_probe)
    monkeypatch.setattr(sfm.stage, "_probe_all", no_probe)
    broken = tmp_path / "calibration.toml"
    broken.write_text("[cam_0]\nmatrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]\n")
    videos = [str(tmp_path / "cam_0.mp4"), str(tmp_path / "cam_1.mp4")]
    given = [broken] if command == "import-calibration" else []
    option = [] if command == "import-calibration" else ["--intrinsics", str(broken)]
    assert main([command, *map(str, given), *videos, "--out", str(tmp_path / "out"), *option]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "calibration.toml: not valid TOML" in err
