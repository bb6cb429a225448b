"""The rerun recording: written from a synthetic scene, read back with RrdReader, checked against inputs."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import rerun as rr

from dynrecon.errors import InputError
from reconstruct.outputs.points import FramePoints
from reconstruct.outputs.recording import BackgroundCloud, RecordingOptions, WorldAxes, log_recording, write_recording
from reconstruct.outputs.recording_parts import (
    LABEL_COLOR,
    OTHER_SOURCE_COLOR,
    TRACK_COLOR,
    _video_samples,
    camera_entity,
    point_colors,
    project,
)
from sfm.cameras import CameraSet, FrameCamera, VideoCameras

# tests/ is on sys.path (pytest imports tests/conftest.py rootdir-relative): the helper imports by name.
import rrd_reader  # isort: skip

VIDEOS = ("left", "right", "top")
FRAMES_PER_VIDEO = 4
POINT_NAMES = ["head", "hand_l", "hand_r", "foot"]
SKELETON = [("head", "hand_l"), ("head", "hand_r"), ("head", "foot")]
K = np.array([[800.0, 0.0, 320.0], [0.0, 780.0, 240.0], [0.0, 0.0, 1.0]])


def rgba(rgb: tuple[int, int, int]) -> int:
    """rerun's packed 0xRRGGBBAA colour."""
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 0xFF


def look_at(center: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at `center` looking at `target`, image y along world +y (down)."""
    z = (target - center) / np.linalg.norm(target - center)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def make_scene(
    seed: int = 0, *, videos: tuple[str, ...] = VIDEOS, frames_per_video: int = FRAMES_PER_VIDEO
) -> tuple[CameraSet, FramePoints]:
    """Cameras on a circle around the origin, moving a little; frames interleaved so no two share a number."""
    rng = np.random.default_rng(seed)
    camera_videos, point_videos, point_frames = [], [], []
    for k, name in enumerate(videos):
        frames = []
        for j in range(frames_per_video):
            number = len(videos) * j + k
            angle = 2 * np.pi * k / len(videos) + 0.02 * j
            center = np.array([4 * np.cos(angle), -1.5, 4 * np.sin(angle)])
            R, t = look_at(center, np.zeros(3))
            frames.append(FrameCamera(frame=number, K=K.copy(), R=R, t=t, time=number / 30))
            point_videos.append(name)
            point_frames.append(number)
        camera_videos.append(VideoCameras(name=name, width=640, height=480, fps=10.0, frames=frames))
    F = len(point_videos)
    xyz = rng.normal(scale=0.4, size=(F, len(POINT_NAMES), 3))
    xyz[1, 2] = np.nan  # "hand_r" not reconstructed in frame 1 of the first video
    observed = np.isfinite(xyz).all(axis=-1)
    points = FramePoints(
        videos=point_videos,
        frames=np.array(point_frames, dtype=np.int64),
        point_names=list(POINT_NAMES),
        xyz=xyz,
        observed=observed,
    )
    return CameraSet(videos=camera_videos), points


def make_tracks(cameras: CameraSet, points: FramePoints):
    """Noise-free 2D observations projected with OpenCV; the first frame of each video is a user's label."""
    from tracking.tracks import Tracks

    rows, sources = [], []
    index = points.index()
    for video in cameras.videos:
        for j, cam in enumerate(video.frames):
            X = points.xyz[index[(video.name, cam.frame)]]
            rvec = cv2.Rodrigues(cam.R)[0]
            uv, _ = cv2.projectPoints(X[np.isfinite(X).all(axis=1)], rvec, cam.t, cam.K, None)
            names = [n for n, x in zip(POINT_NAMES, X, strict=True) if np.isfinite(x).all()]
            for name, (u, v) in zip(names, uv.reshape(-1, 2), strict=True):
                rows.append((video.name, cam.frame, name, float(u), float(v)))
                sources.append("label" if j == 0 else "track")
    return Tracks.from_rows(rows, source=sources)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    cameras, points = make_scene()
    tracks = make_tracks(cameras, points)
    F = points.num_frames
    residual = np.linspace(0.5, 2.0, F)
    residual[3] = np.nan
    global_time = 0.01 * np.arange(F)[np.argsort(points.frames, kind="stable").argsort()]
    background = BackgroundCloud(
        xyz=np.random.default_rng(1).normal(size=(50, 3)) * 5, colors=np.full((50, 3), 128, np.uint8)
    )
    path = write_recording(
        tmp_path_factory.mktemp("rec") / "recording.rrd",
        cameras=cameras,
        points=points,
        tracks=tracks,
        skeleton=SKELETON,
        residual=residual,
        global_time=global_time,
        background=background,
    )
    return dict(path=path, cameras=cameras, points=points, tracks=tracks, residual=residual, global_time=global_time)


def rows_per_timeline(path: Path, entity: str) -> dict[str, int]:
    counts: dict[str, int] = {}
    for chunk in rrd_reader.chunks(path):
        if chunk.entity == entity and not chunk.static:
            for name in chunk.timelines:
                counts[name] = counts.get(name, 0) + chunk.num_rows
    return counts


def test_entity_paths_and_timelines(scene: dict) -> None:
    path = scene["path"]
    expected = {"/world", "/world/background", "/world/points", "/metrics/residual"}
    for video in VIDEOS:
        expected |= {
            f"/world/cameras/{video}",
            f"/world/cameras/{video}/image/tracks",
            f"/world/cameras/{video}/image/reprojection",
        }
    assert rrd_reader.entities(path) - {"/__properties"} == expected
    assert rrd_reader.timelines(path) == {f"frame:{v}" for v in VIDEOS} | {"global_time"}


def test_row_counts_per_entity_and_timeline(scene: dict) -> None:
    path, F = scene["path"], scene["points"].num_frames
    per_video = {f"frame:{v}": FRAMES_PER_VIDEO for v in VIDEOS}
    assert rows_per_timeline(path, "/world/points") == {**per_video, "global_time": F}
    for video in VIDEOS:
        own = {f"frame:{video}": FRAMES_PER_VIDEO, "global_time": FRAMES_PER_VIDEO}
        assert rows_per_timeline(path, f"/world/cameras/{video}") == own
        assert rows_per_timeline(path, f"/world/cameras/{video}/image/tracks") == own
        assert rows_per_timeline(path, f"/world/cameras/{video}/image/reprojection") == own
    residual_rows = rows_per_timeline(path, "/metrics/residual")
    assert residual_rows["global_time"] == F - 1  # the NaN residual is left out, not plotted as 0
    assert sum(n for name, n in residual_rows.items() if name.startswith("frame:")) == F - 1


def test_point_positions_labels_and_ids_equal_input(scene: dict) -> None:
    path, points = scene["path"], scene["points"]
    for i, (video, frame) in enumerate(zip(points.videos, points.frames, strict=True)):
        timeline = f"frame:{video}"
        positions, labels, ids = (
            rrd_reader.component_rows(path, "/world/points", f"Points3D:{component}", timeline)[int(frame)]
            for component in ("positions", "labels", "keypoint_ids")
        )
        finite = np.isfinite(points.xyz[i]).all(axis=1)
        # float32 in the file
        np.testing.assert_allclose(positions, points.xyz[i][finite], rtol=1e-6, atol=1e-6)
        assert labels == [n for n, keep in zip(POINT_NAMES, finite, strict=True) if keep]
        assert ids.tolist() == np.flatnonzero(finite).tolist()
    frame1 = rrd_reader.component_rows(path, "/world/points", "Points3D:labels", f"frame:{VIDEOS[0]}")
    assert "hand_r" not in frame1[int(points.frames[1])]  # NaN point left out


def test_points_on_global_time(scene: dict) -> None:
    path, points, global_time = scene["path"], scene["points"], scene["global_time"]
    rows = rrd_reader.component_rows(path, "/world/points", "Points3D:positions", "global_time")
    times = np.array(sorted(rows))
    np.testing.assert_allclose(times, np.sort(global_time), atol=1e-9)
    i = 5
    got = rows[min(rows, key=lambda t: abs(t - global_time[i]))]
    np.testing.assert_allclose(got, points.xyz[i][np.isfinite(points.xyz[i]).all(axis=1)], atol=1e-6)


def test_camera_transform_and_pinhole_equal_input(scene: dict) -> None:
    path, cameras = scene["path"], scene["cameras"]
    for video in cameras.videos:
        entity = "/" + camera_entity(video.name)
        timeline = f"frame:{video.name}"
        translation = rrd_reader.component_rows(path, entity, "Transform3D:translation", timeline)
        mat = rrd_reader.component_rows(path, entity, "Transform3D:mat3x3", timeline)
        relation = rrd_reader.component_rows(path, entity, "Transform3D:relation", timeline)
        assert sorted(translation) == [f.frame for f in video.frames]
        for cam in video.frames:
            np.testing.assert_allclose(translation[cam.frame].ravel(), cam.t, atol=1e-6)
            # rerun stores Mat3x3 column-major
            np.testing.assert_allclose(mat[cam.frame].reshape(3, 3).T, cam.R, atol=1e-6)
            assert relation[cam.frame].tolist() == [2]  # TransformRelation.ChildFromParent
        K_flat = rrd_reader.static_component(path, entity, "Pinhole:image_from_camera")
        np.testing.assert_allclose(np.array(K_flat).reshape(3, 3).T, K)
        assert rrd_reader.static_component(path, entity, "Pinhole:resolution") == [[640.0, 480.0]]


def test_reprojection_equals_noise_free_tracks(scene: dict) -> None:
    """The tracks were projected by OpenCV from the same 3D points, so both overlays must coincide."""
    path = scene["path"]
    for video in VIDEOS:
        base = f"/world/cameras/{video}/image"
        reproj, tracks = (
            rrd_reader.component_rows(path, f"{base}/{entity}", "Points2D:positions", f"frame:{video}")
            for entity in ("reprojection", "tracks")
        )
        assert sorted(reproj) == sorted(tracks) and len(reproj) == FRAMES_PER_VIDEO
        for frame in reproj:
            np.testing.assert_allclose(reproj[frame], tracks[frame], atol=1e-3)


def test_track_colours_by_source(scene: dict) -> None:
    path = scene["path"]
    for video in VIDEOS:
        entity = f"/world/cameras/{video}/image/tracks"
        colors = rrd_reader.component_rows(path, entity, "Points2D:colors", f"frame:{video}")
        first, *rest = sorted(colors)
        assert set(colors[first].tolist()) == {rgba(LABEL_COLOR)}
        for frame in rest:
            assert set(colors[frame].tolist()) == {rgba(TRACK_COLOR)}


def test_annotation_context_and_view_coordinates(scene: dict) -> None:
    path = scene["path"]
    ((entry,),) = rrd_reader.static_component(path, "/world", "AnnotationContext:context")
    assert entry["class_id"] == 0
    description = entry["class_description"]
    assert [k["label"] for k in description["keypoint_annotations"]] == POINT_NAMES
    assert [k["color"] for k in description["keypoint_annotations"]] == [
        rgba(tuple(int(x) for x in c)) for c in point_colors(len(POINT_NAMES))
    ]
    connections = [(c["keypoint0"], c["keypoint1"]) for c in description["keypoint_connections"]]
    assert connections == [(0, 1), (0, 2), (0, 3)]
    assert rrd_reader.static_component(path, "/world", "ViewCoordinates:xyz") == [[3, 2, 5]]  # R, D, F


def test_residual_values(scene: dict) -> None:
    path, points, residual = scene["path"], scene["points"], scene["residual"]
    for i, (video, frame) in enumerate(zip(points.videos, points.frames, strict=True)):
        rows = rrd_reader.component_rows(path, "/metrics/residual", "Scalars:scalars", f"frame:{video}")
        if np.isfinite(residual[i]):
            assert rows[int(frame)].tolist() == pytest.approx([residual[i]])
        else:
            assert int(frame) not in rows


def test_background_is_static(scene: dict) -> None:
    path = scene["path"]
    assert all(c.static for c in rrd_reader.chunks(path) if c.entity == "/world/background")
    assert len(rrd_reader.static_component(path, "/world/background", "Points3D:positions")) == 50


def test_default_blueprint(scene: dict) -> None:
    views = rrd_reader.blueprint_views(scene["path"])
    assert sorted(views) == sorted(
        [("3D", "world"), ("residual", "metrics")] + [(v, f"world/cameras/{v}") for v in VIDEOS]
    )


def test_rrd_verify_passes(scene: dict) -> None:
    result = rrd_reader.verify(scene["path"])
    assert result.returncode == 0, result.stderr


def test_minimal_recording_and_escaped_video_names(tmp_path: Path) -> None:
    """Only cameras and points: no tracks, metrics or global time; odd video names still make valid paths."""
    cameras, points = make_scene(videos=("cam 1/left", "cam.2"), frames_per_video=3)
    path = write_recording(tmp_path / "minimal.rrd", cameras=cameras, points=points)
    assert rrd_reader.timelines(path) == {"frame:cam 1/left", "frame:cam.2"}
    found = rrd_reader.entities(path) - {"/__properties"}
    assert len(found) == 6 and "/world/points" in found and not any("metrics" in e for e in found)
    assert "/" + camera_entity("cam 1/left") in found
    # no residual: the blueprint has no time-series view
    assert sorted(rrd_reader.blueprint_views(path)) == [
        ("3D", "world"),
        ("cam 1/left", r"world/cameras/cam\ 1\/left"),
        ("cam.2", "world/cameras/cam.2"),
    ]
    assert rrd_reader.verify(path).returncode == 0


def test_varying_intrinsics_logged_per_frame(tmp_path: Path) -> None:
    cameras, points = make_scene(frames_per_video=3)
    zoom = cameras.videos[0].frames
    for j, cam in enumerate(zoom):
        cam.K = cam.K.copy()
        cam.K[0, 0] = cam.K[1, 1] = 700.0 + 50 * j
    path = write_recording(
        tmp_path / "zoom.rrd", cameras=cameras, points=points, options=RecordingOptions(blueprint=False)
    )
    assert rrd_reader.blueprint_views(path) == []
    entity = "/" + camera_entity(VIDEOS[0])
    rows = rrd_reader.component_rows(path, entity, "Pinhole:image_from_camera", f"frame:{VIDEOS[0]}")
    assert [rows[c.frame].reshape(3, 3).T[0, 0] for c in zoom] == [700.0, 750.0, 800.0]
    assert rrd_reader.static_component(path, entity, "Pinhole:resolution") == [[640.0, 480.0]]


def test_project_matches_opencv_with_distortion() -> None:
    rng = np.random.default_rng(3)
    X = rng.normal(size=(2, 30, 3)) + np.array([0.0, 0.0, 6.0])
    dist = np.array([[-0.2, 0.05, 0.001, -0.002, 0.01], [0.1, 0.0, 0.0, 0.0, 0.0]])
    R = np.stack([cv2.Rodrigues(np.array([0.1, -0.2, 0.05]) * (i + 1))[0] for i in range(2)])
    t = np.array([[0.1, 0.2, 0.3], [-0.2, 0.0, 0.5]])
    Ks = np.stack([K, K])
    uv, in_front = project(X, Ks, R, t, dist)
    assert in_front.all()
    for i in range(2):
        expected, _ = cv2.projectPoints(X[i], cv2.Rodrigues(R[i])[0], t[i], K, dist[i])
        np.testing.assert_allclose(uv[i], expected.reshape(-1, 2), atol=1e-9)
    behind = project(-X, Ks, R, t)[1]
    assert not behind.all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("skeleton", "unknown point 'elbow'"),
        ("residual", "residual has shape (3,)"),
        ("global_time", "global_time has shape"),
        ("frame", "have no camera"),
    ],
)
def test_bad_inputs_raise_before_writing(tmp_path: Path, change: str, message: str) -> None:
    cameras, points = make_scene()
    kwargs: dict = {}
    if change == "skeleton":
        kwargs["skeleton"] = [("head", "elbow")]
    elif change == "residual":
        kwargs["residual"] = np.zeros(3)
    elif change == "global_time":
        kwargs["global_time"] = np.zeros((points.num_frames, 2))
    else:
        points.frames[2] = 999
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        write_recording(tmp_path / "bad.rrd", cameras=cameras, points=points, **kwargs)
    assert list(tmp_path.iterdir()) == []  # no partial file left behind


def test_write_speed_2000_frames_44_points(tmp_path: Path) -> None:
    """F = 2000 x P = 44 must stay a small part of a solve (batch logging, not one call per row)."""
    names = [f"p{i}" for i in range(44)]
    cameras, points = make_scene(videos=("a", "b", "c", "d"), frames_per_video=500)
    rng = np.random.default_rng(5)
    points = FramePoints(
        videos=points.videos,
        frames=points.frames,
        point_names=names,
        xyz=rng.normal(size=(2000, 44, 3)),
        observed=np.ones((2000, 44), bool),
    )
    start = time.perf_counter()
    path = write_recording(
        tmp_path / "big.rrd",
        cameras=cameras,
        points=points,
        skeleton=[(names[i], names[i + 1]) for i in range(43)],
        residual=rng.random(2000),
        global_time=np.arange(2000) / 120.0,
    )
    elapsed = time.perf_counter() - start
    assert elapsed < 5.0, f"{elapsed:.2f} s"
    assert rows_per_timeline(path, "/world/points")["global_time"] == 2000


def write_video(path: Path, fourcc: str, num_frames: int, fps: float = 10.0) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (64, 48))
    assert writer.isOpened(), f"OpenCV cannot write {fourcc}"
    for i in range(num_frames):
        writer.write(np.full((48, 64, 3), 10 * i, np.uint8))
    writer.release()
    return path


def test_video_files_embedded_with_frame_references(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A vp09 video is embedded and each posed frame references its timestamp; mp4v (which rerun cannot play),
    too-short files and unknown videos are skipped with a warning, and the rest of the recording is intact."""
    cameras, points = make_scene()  # posed frames: left 0,3,6,9; right 1,4,7,10; top 2,5,8,11
    files = {
        # at the scene's 30 fps: frame n's decoder time (cameras.json) is its sample's
        "left": write_video(tmp_path / "left.mp4", "vp09", 12, fps=30.0),
        "right": write_video(tmp_path / "right.mp4", "mp4v", 12, fps=30.0),
        "top": write_video(tmp_path / "top.mp4", "vp09", 6, fps=30.0),
        "nobody": tmp_path / "nobody.mp4",
    }
    with caplog.at_level("WARNING", logger="reconstruct.outputs.recording"):
        path = write_recording(
            tmp_path / "video.rrd",
            cameras=cameras,
            points=points,
            video_files=files,
            global_time=np.arange(points.num_frames) * 0.1,
        )
    warnings = caplog.text
    assert "right.mp4: video not embedded" in warnings and "mp4v" in warnings
    assert "top.mp4 has 6 frames" in warnings and "'nobody'" in warnings
    found = rrd_reader.entities(path)
    assert "/world/cameras/left/image" in found and "/world/cameras/right/image" not in found
    refs = rrd_reader.component_rows(path, "/world/cameras/left/image", "VideoFrameReference:timestamp", "frame:left")
    assert {f: round(int(v[0]) / 1e6) for f, v in refs.items()} == {0: 0, 3: 100, 6: 200, 9: 300}  # ms
    top = rrd_reader.component_rows(path, "/world/cameras/top/image", "VideoFrameReference:timestamp", "global_time")
    assert len(top) == 2  # frames 2 and 5; 8 and 11 lie beyond the 6-frame file
    blob = rrd_reader.static_component(path, "/world/cameras/left/image", "AssetVideo:blob")
    assert bytes(blob[0]) == files["left"].read_bytes()
    assert rrd_reader.verify(path).returncode == 0


def test_world_axes_option(tmp_path: Path) -> None:
    cameras, points = make_scene(frames_per_video=2)
    path = write_recording(
        tmp_path / "zup.rrd", cameras=cameras, points=points, options=RecordingOptions(world_axes=WorldAxes.Z_UP)
    )
    assert rrd_reader.static_component(path, "/world", "ViewCoordinates:xyz") == [[3, 5, 1]]  # R, F, U


def test_log_recording_into_any_stream(tmp_path: Path) -> None:
    """The core function only needs a RecordingStream: here an in-memory sink, saved and read back."""
    cameras, points = make_scene(frames_per_video=2)
    rec = rr.RecordingStream("dynrecon-test")
    memory = rec.memory_recording()
    log_recording(rec, cameras=cameras, points=points, residual=np.ones(points.num_frames))
    rec.flush()
    path = tmp_path / "memory.rrd"
    path.write_bytes(memory.drain_as_bytes())
    assert rows_per_timeline(path, "/metrics/residual") == {f"frame:{v}": 2 for v in VIDEOS}
    assert rows_per_timeline(path, "/world/points") == {f"frame:{v}": 2 for v in VIDEOS}


def test_unknown_track_source_gets_its_own_colour(tmp_path: Path) -> None:
    cameras, points = make_scene(frames_per_video=1)
    tracks = make_tracks(cameras, points)
    tracks.extra["source"] = ["label", "track", "detector"] + ["track"] * (len(tracks) - 3)
    path = write_recording(tmp_path / "src.rrd", cameras=cameras, points=points, tracks=tracks)
    colors = rrd_reader.component_rows(
        path, f"/world/cameras/{VIDEOS[0]}/image/tracks", "Points2D:colors", f"frame:{VIDEOS[0]}"
    )[0]
    assert colors[:3].tolist() == [rgba(LABEL_COLOR), rgba(TRACK_COLOR), rgba(OTHER_SOURCE_COLOR)]


def test_frames_take_their_own_samples_across_a_damaged_stretch() -> None:
    """A file with 30 samples at 30 fps whose samples 10-14 do not decode: decoded frame 10 is sample 15 (by its
    decoder time), not sample 10; an intact file maps frame n to sample n."""
    timestamps = (np.arange(30) * 1e9 / 30).astype(np.int64)
    decoded = np.r_[0:10, 15:30]  # the samples the decoder returned, numbered 0..24 as frames
    frames = np.arange(len(decoded))
    samples = _video_samples(timestamps, frames, list(decoded / 30.0))
    np.testing.assert_array_equal(samples, decoded)
    np.testing.assert_array_equal(_video_samples(timestamps, np.arange(30), list(np.arange(30) / 30.0)), np.arange(30))
