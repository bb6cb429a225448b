"""`register`'s per-video steps (`sfm.per_video`) as separate processes that share only files: the same cameras as
the serial stage, and the file forms that carry a video's plan and poses from one process to the next."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sfm.cameras import read_cameras
from sfm.frames import Resize
from sfm.keyframes import KeyframeChoice, KeyframeReason, even_choice
from sfm.layout import Layout
from sfm.options import RegisterOptions
from sfm.per_video import capture_facts, extract_videos, localize_video, prepare_video
from sfm.plan import FramePose, VideoPlan
from sfm.plan_io import PreparedVideo, StepNotes, read_poses, read_prepared, write_poses, write_prepared
from sfm.stage import capture_tracks, finish_capture, map_capture, run
from sfm.static import MotionTest
from sfm.synthetic.demo import render_demo, sphere_tracks, three_cameras
from sfm.video import ProbedVideo, probe_video
from tracking.tracks import write_tracks


def _plan(tmp_path: Path) -> VideoPlan:
    info = ProbedVideo(
        path=tmp_path / "cam0.mp4",
        name="cam0",
        width=640,
        height=480,
        times=np.arange(7) / 29.97 + 1e-9,
        nominal_fps=29.97,
        rotation=90,
        expected_frames=8,
        missing="1 frame missing",
    )
    motion = MotionTest(static=False, reason="moved", frames=[0, 3], shifts=[0.1, 7.25], tracked=[1.0, 0.5], corners=9)
    choice = KeyframeChoice(
        method="content",
        frames=np.array([0, 4, 6]),
        reasons=[KeyframeReason.FIRST, KeyframeReason.MOTION, KeyframeReason.LAST],
        candidates=3,
        settings={"motion": 0.05, "survival": 0.5},
    )
    return VideoPlan(
        info=info,
        resize=Resize.for_video(info, 333),
        sfm_frames=choice.frames,
        wanted=np.arange(7),
        motion=motion,
        keyframes=choice,
    )


def test_a_plan_file_reads_back_as_the_plan(tmp_path: Path) -> None:
    plan = dataclasses.replace(_plan(tmp_path), motion_given=True)
    notes = StepNotes(warnings=["a warning"], timings={"decode": 0.25}, reused=["keyframes cam0"])
    path = write_prepared(tmp_path / "plan.json", PreparedVideo(plan=plan, images=["cam0/a.jpg"], masks=2, notes=notes))
    back = read_prepared(path)
    assert back.images == ["cam0/a.jpg"] and back.masks == 2 and back.notes == notes
    assert back.plan.info.times.tolist() == plan.info.times.tolist()  # bit for bit: the times go into cameras.json
    assert {k: v for k, v in vars(back.plan.info).items() if k != "times"} == {
        k: v for k, v in vars(plan.info).items() if k != "times"
    }
    assert back.plan.resize == plan.resize and back.plan.motion == plan.motion
    assert back.plan.motion_given == plan.motion_given
    assert back.plan.sfm_frames.tolist() == [0, 4, 6] and back.plan.wanted.tolist() == list(range(7))
    assert back.plan.keyframes is not None and plan.keyframes is not None
    assert back.plan.keyframes.to_json() == plan.keyframes.to_json()
    assert back.plan.keyframes.reasons == plan.keyframes.reasons

    even = VideoPlan(info=plan.info, resize=plan.resize, sfm_frames=np.array([0, 3]), wanted=np.arange(7))
    even.keyframes = even_choice(even.sfm_frames)
    back = read_prepared(write_prepared(tmp_path / "even.json", PreparedVideo(plan=even, images=[], masks=0)))
    assert back.plan.keyframes is not None and back.plan.keyframes.to_json() == even.keyframes.to_json()
    assert back.plan.motion is None and not back.plan.static


def test_a_poses_file_reads_back_bit_for_bit(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    poses = {}
    for frame in range(50):
        quat = rng.normal(size=4)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(quat / np.linalg.norm(quat)), rng.normal(size=3))
        K = np.array([[rng.uniform(300, 900), 0, 320.5], [0, rng.uniform(300, 900), 240.25], [0, 0, 1]])
        poses[frame] = FramePose(
            pose=pose, source="tracked", error=float(rng.uniform()), intrinsics=(K, rng.normal(size=4)), inliers=31
        )
    poses[50] = FramePose(pose=None, reason="tracking lost the features; SIFT: no features")
    back, notes = read_poses(write_poses(tmp_path / "poses.json", "cam0", poses, StepNotes(warnings=["w"])))
    assert notes.warnings == ["w"] and sorted(back) == sorted(poses)
    for frame, pose in poses.items():
        got = back[frame]
        assert (got.reason, got.source, got.error, got.inliers) == (pose.reason, pose.source, pose.error, pose.inliers)
        if pose.pose is None:
            assert got.pose is None and got.intrinsics is None
            continue
        assert got.pose is not None and got.intrinsics is not None and pose.intrinsics is not None
        assert np.array_equal(got.pose.rotation.matrix(), pose.pose.rotation.matrix())
        assert np.array_equal(got.pose.translation, pose.pose.translation)
        assert np.array_equal(got.intrinsics[0], pose.intrinsics[0])
        assert np.array_equal(got.intrinsics[1], pose.intrinsics[1])


def _prepare(video: Path, out: Path, options: RegisterOptions, names: list[str]) -> str:
    prepare_video(probe_video(video), out, options, capture_tracks(options, out, names))
    return video.stem


def _extract(video: str, names: list[str], out: Path, options: RegisterOptions) -> None:
    extract_videos(out, [video], options, capture_facts(out, names))


@pytest.mark.slow
def test_per_video_steps_in_separate_processes_give_the_serial_cameras(tmp_path: Path) -> None:
    """The synthetic room (3 moving cameras, the subject masked by its tracks), COLMAP on one thread: the serial
    stage and the per-video steps in worker processes (videos in reverse order, two at a time) write the same
    cameras.json, byte for byte."""
    videos = render_demo(tmp_path / "videos", three_cameras(480, 360, frames=(10, 8, 6)))
    paths = [v.path for v in videos]
    options = RegisterOptions(long_side=480, max_frames=6, max_features=1500, mask_radius=70, num_threads=1)
    serial, split = tmp_path / "serial", tmp_path / "split"
    for ws in (serial, split):
        write_tracks(ws / "tracks.csv", sphere_tracks(videos))
    run(paths, serial, options)

    names = [p.stem for p in paths]
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_prepare, reversed(paths), [split] * 3, [options] * 3, [names] * 3))
        list(pool.map(_extract, reversed(names), [names] * 3, [split] * 3, [options] * 3))
        map_capture(split, names, options)
        list(pool.map(localize_video, [split] * 3, reversed(names), [options] * 3))
    finish_capture(split, names, options, capture_tracks(options, split, names))

    assert (split / "cameras.json").read_bytes() == (serial / "cameras.json").read_bytes()
    assert (split / "background.ply").read_bytes() == (serial / "background.ply").read_bytes()
    layout = Layout(split)
    assert all(layout.features(name).exists() and layout.poses(name).exists() for name in names)
    report = json.loads((split / "register_report.json").read_text())
    assert report["ok"] and set(report["timings_s"]) >= {"decode", "extract", "match", "map", "localize"}


def test_a_tracked_video_found_moving_and_left_unposed_is_named_with_the_way_out(tmp_path: Path) -> None:
    """A tripod whose view a held board fills can measure as moving; the subject path poses static cameras only:
    the report names it, its measured reason and --camera-motion static. Not when the user chose the motion, when
    nothing is tracked in it, or when it was posed."""
    from sfm.options import CameraMotion
    from sfm.stage import _moving_hint
    from tracking.tracks import Tracks

    plan = _plan(tmp_path)
    tracks = Tracks.from_rows([("cam0", 0, "corner_0", 1.0, 2.0)])
    hint = _moving_hint([plan], [], tracks, RegisterOptions())
    assert hint is not None and hint.startswith("cam0 measured as moving (cam0: moved)")
    assert hint.endswith("register (or run) again with --camera-motion static")
    assert _moving_hint([plan], [], tracks, RegisterOptions(camera_motion=CameraMotion.MOVING)) is None
    assert _moving_hint([plan], [plan], tracks, RegisterOptions()) is None
    # posed by the background alone in a registration that fails (caliscope's port_1, which a person walking away
    # hid in its first samples, posed from its own frames): named, as the way out may be static
    failing = _moving_hint([plan], [plan], tracks, RegisterOptions(), failing=True)
    assert failing is not None and "left to the background" in failing and "--camera-motion static" in failing
    # in one failing registration, each video is said with its own fate
    other = dataclasses.replace(plan, info=dataclasses.replace(plan.info, name="cam1"))
    both = Tracks.from_rows([("cam0", 0, "a", 1.0, 2.0), ("cam1", 0, "a", 1.0, 2.0)])
    mixed = _moving_hint([plan, other], [plan], both, RegisterOptions(), failing=True)
    assert mixed is not None and "cam1 not posed, cam0 left to the background;" in mixed
    assert _moving_hint([plan], [], Tracks.from_rows([("cam1", 0, "a", 1.0, 2.0)]), RegisterOptions()) is None
    assert _moving_hint([plan], [], None, RegisterOptions()) is None


def test_a_failure_names_a_camera_motion_the_motion_test_measured_otherwise(tmp_path: Path) -> None:
    """--camera-motion static on a video measured moving: a failed registration names it and --camera-motion auto;
    not where the user's word agrees, nor where nothing was measured (an untextured view)."""
    from sfm.options import CameraMotion
    from sfm.stage import _given_motion_hint

    plan = _plan(tmp_path)  # measured moving
    static = RegisterOptions(camera_motion=CameraMotion.STATIC)
    forced = dataclasses.replace(plan, static=True, motion_given=True)
    hint = _given_motion_hint([forced], static)
    assert hint == (
        "--camera-motion static was given, but the motion test measured otherwise (cam0: moved): register again "
        "with --camera-motion auto"
    )
    assert _given_motion_hint([dataclasses.replace(forced, static=False)], static) is None
    assert _given_motion_hint([dataclasses.replace(plan, static=True)], RegisterOptions()) is None
    unmeasured = dataclasses.replace(plan.motion, shifts=[], frames=[]) if plan.motion is not None else None
    assert _given_motion_hint([dataclasses.replace(forced, motion=unmeasured)], static) is None


def test_a_declared_clock_goes_into_cameras_json_when_the_subject_path_found_none(tmp_path: Path) -> None:
    """`register --synchronized` (or `--offsets`) with every video posed by the background: cameras.json carries the
    declared clock (clock_offset 0, or the given one), which the solve then tests; without the declaration, or where
    the subject path found the clocks, those are written."""
    from sfm.stage import _export

    plan = _plan(tmp_path)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, 0, 0, 1])), np.zeros(3))
    results = {"cam0": {f: FramePose(pose=pose, source="static", intrinsics=(K, None)) for f in range(7)}}
    points = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    for n, (declared, subject, expected, as_declared) in enumerate(
        (
            ({"cam0": 0.0}, None, 0.0, True),
            ({"cam0": -0.125}, None, -0.125, True),
            (None, None, None, False),
            ({"cam0": 0.0}, {"cameras": [{"name": "cam0", "offset_s": 0.25}]}, 0.25, False),  # an estimate
        )
    ):
        path = _export([plan], results, points, subject, {}, tmp_path / str(n), declared)
        assert read_cameras(path).videos[0].clock_offset == expected
        assert read_cameras(path).videos[0].clock_declared is as_declared


def test_a_camera_motion_the_motion_test_contradicts_is_kept_and_warned(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """`--camera-motion static` on a handheld video: the user's word is kept (one pose for every frame), and the
    warning, which also goes into register_report.json's warnings, names the video and the measured motion."""
    import logging

    from sfm.options import CameraMotion
    from sfm.per_video import collected, plan_video
    from sfm.resume import StepLog

    video = Path(__file__).resolve().parents[2] / "data_samples" / "video_sample" / "cam0.mp4"  # handheld
    info = probe_video(video)
    caplog.set_level(logging.WARNING)
    notes = StepNotes()
    with collected(notes):
        plan = plan_video(info, None, RegisterOptions(camera_motion=CameraMotion.STATIC), StepLog(tmp_path), notes)
    assert plan.static and plan.motion_given and len(plan.sfm_frames) == 0
    assert plan.motion is not None and not plan.motion.static  # the measurement is kept for the report
    warned = [w for w in notes.warnings if "--camera-motion static given" in w]
    assert len(warned) == 1 and warned[0].startswith("cam0: ") and "moving" in warned[0] and "auto" in warned[0]
    notes = StepNotes()
    with collected(notes):
        plan_video(info, None, RegisterOptions(camera_motion=CameraMotion.MOVING), StepLog(tmp_path), notes)
    assert not [w for w in notes.warnings if "--camera-motion" in w]  # the test agrees: nothing said
    # an untextured view (a grey stand-in for a video one has only detections of): nothing measured, nothing said
    import cv2

    grey = tmp_path / "grey.mp4"
    writer = cv2.VideoWriter(str(grey), cv2.VideoWriter.fourcc(*"mp4v"), 10.0, (96, 64))
    for _ in range(6):
        writer.write(np.full((64, 96, 3), 90, np.uint8))
    writer.release()
    notes = StepNotes()
    with collected(notes):
        flat = plan_video(
            probe_video(grey), None, RegisterOptions(camera_motion=CameraMotion.STATIC), StepLog(tmp_path), notes
        )
    assert flat.static and flat.motion is not None and not flat.motion.shifts
    assert not [w for w in notes.warnings if "--camera-motion" in w]
