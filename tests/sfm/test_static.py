"""Static-camera detection and background images (`sfm.static`), and `register` on a mixed static + handheld
capture of the synthetic room (ground truth known)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from sfm.cameras import CameraSet, read_cameras
from sfm.evaluate import compare
from sfm.frames import Resize
from sfm.static import background_image, measure_motion, sample_frames
from sfm.synthetic.demo import mixed_cameras, render_demo, sphere_tracks
from sfm.synthetic.room import Room, render
from sfm.video import probe_video, read_frames
from tracking.tracks import write_tracks

ROOM_DIAGONAL = float(np.linalg.norm(Room(textures=[np.zeros((1, 1, 3), np.uint8)] * 6).size))


@pytest.fixture(scope="module")
def mixed(tmp_path_factory: pytest.TempPathFactory) -> list:
    return render_demo(tmp_path_factory.mktemp("mixed"), mixed_cameras(480, 360, frames=12))


def test_motion_test_tells_static_from_handheld(mixed: list) -> None:
    decisions = {}
    for video in mixed:
        test = measure_motion(probe_video(video.path))
        decisions[video.cameras.name] = test
        assert len(test.frames) == 12 and test.corners >= 20
    # The spheres move through the static views: the test must see through them.
    assert decisions["cam0"].static and decisions["cam2"].static
    assert max(decisions["cam0"].shifts) < 0.5 and max(decisions["cam2"].shifts) < 0.5
    assert not decisions["cam1"].static and "moving" in decisions["cam1"].reason
    assert max(decisions["cam1"].shifts) > 5
    assert decisions["cam0"].to_json()["static"] is True


def test_background_image_removes_the_moving_subject(mixed: list) -> None:
    video = mixed[0]
    info = probe_video(video.path)
    median = background_image(info, sample_frames(info, 24), Resize.for_video(info, 480)).astype(float)
    frame = video.cameras.frames[0]
    empty, _, _ = render(Room(seed=0), frame.K, frame.R, frame.t, info.width, info.height, None)
    error = np.abs(median - empty.astype(float)).mean(axis=2)  # (H, W): video compression noise at best
    covered = (video.object_ids >= 0).mean(axis=0)  # (H, W) share of frames a sphere covers the pixel
    never, sometimes = covered == 0, (covered > 0) & (covered < 0.4)
    assert sometimes.mean() > 0.005
    # Where a sphere passed in a few frames, the median shows the room behind it as well as where none passed.
    assert np.median(error[sometimes]) < 1.5 * np.median(error[never]) + 3
    _, first = next(read_frames(info.path, np.array([0])))
    in_sphere = video.object_ids[0] >= 0
    assert np.median(np.abs(first.astype(float) - empty).mean(axis=2)[in_sphere]) > 3 * np.median(error[sometimes])


@pytest.mark.slow
def test_register_mixed_static_and_handheld(mixed: list, tmp_path: Path) -> None:
    truth = CameraSet(videos=[v.cameras for v in mixed])
    ws = tmp_path / "ws"
    write_tracks(ws / "tracks.csv", sphere_tracks(mixed))  # masks the spheres out of SfM
    args = [
        "register",
        *(str(v.path) for v in mixed),
        "--out",
        str(ws),
        "--long-side",
        "480",
        "--threads",
        "1",
        "--max-frames",
        "12",
        "--max-features",
        "2000",
        "--background-features",
        "4000",
        "--mask-radius",
        "40",
    ]
    assert main(args) == 0
    report = json.loads((ws / "register_report.json").read_text())
    by_name = {v["name"]: v for v in report["videos"]}
    assert by_name["cam0"]["camera"] == by_name["cam2"]["camera"] == "static"
    assert by_name["cam1"]["camera"] == "moving"
    assert by_name["cam0"]["posed_by"].startswith("static") and by_name["cam1"]["posed_by"].startswith("background")
    assert by_name["cam0"]["sfm_frames"] == 0 and by_name["cam0"]["registered_by_static"] == 12
    cameras = read_cameras(ws / "cameras.json")
    for name in ("cam0", "cam2"):  # one pose for every frame of a static video
        frames = cameras.video(name).frames
        assert len(frames) == 12 and all(np.array_equal(f.R, frames[0].R) for f in frames)
    errors = compare(cameras, truth)
    assert len(errors.keys) == 36
    spread = np.ptp(np.array([f.center for v in truth.videos for f in v.frames]), axis=0).max()
    assert errors.center_errors.max() < 0.02 * spread
    assert errors.rotation_errors_deg.max() < 1.0


def test_a_bumped_static_camera_is_reported_and_its_background_uses_the_main_position(
    mixed: list, tmp_path: Path
) -> None:
    # the tripod of cam0 knocked 2 px sideways for the first 5 of 12 frames: still static, but said
    info = probe_video(mixed[0].path)
    path = tmp_path / "bumped.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (info.width, info.height))
    shift = np.float32([[1, 0, 2.0], [0, 1, 0]])
    for frame, image in read_frames(info.path, np.arange(info.num_frames)):
        writer.write(cv2.warpAffine(image, shift, (info.width, info.height)) if frame < 5 else image)
    writer.release()
    test = measure_motion(probe_video(path))
    assert test.static
    assert test.settled == list(range(5, 12))
    assert test.moved is not None and "frames 0-4" in test.moved and "bumped" in test.moved
    assert 1.5 < float(test.moved.split(" sit ")[1].split(" px")[0]) < 2.5
    assert test.to_json()["moved"] == test.moved
    undisturbed = measure_motion(info)
    assert undisturbed.moved is None and undisturbed.settled == undisturbed.frames


def test_one_damaged_frame_does_not_make_a_static_camera_moving(mixed: list, tmp_path: Path) -> None:
    """A decoder's smeared frame (here frame 6 of cam0 shifted 12 px and blurred) is one odd sample: the camera
    stays static and the report says which sample was ignored; the handheld camera is still moving."""
    info = probe_video(mixed[0].path)
    path = tmp_path / "damaged.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (info.width, info.height))
    shift = np.float32([[1, 0, 12.0], [0, 1, 5.0]])
    for frame, image in read_frames(info.path, np.arange(info.num_frames)):
        smeared = cv2.GaussianBlur(cv2.warpAffine(image, shift, (info.width, info.height)), (9, 9), 3)
        writer.write(smeared if frame == 6 else image)
    writer.release()
    test = measure_motion(probe_video(path))
    assert test.static and "one odd sample ignored: frame 6" in test.reason, test.reason
    assert not measure_motion(probe_video(mixed[1].path)).static


def _occluded_video(
    source: Path, path: Path, shifts: dict[int, int], *, textured: bool, whole: bool = False
) -> dict[int, np.ndarray]:
    """`source` with a rectangle over 70 % of the view in the frames of `shifts` (frame -> its x offset in
    pixels; a board held close, textured, or a flat grey occluder; `whole`: the whole view grey); returns its
    corners per frame (what a board's tracks give)."""
    info = probe_video(source)
    w, h = info.width, info.height
    texture = cv2.resize(np.random.default_rng(3).integers(0, 255, (h // 8, w // 8, 3), np.uint8), (w, h))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (w, h))
    corners = {}
    for frame, image in read_frames(source, np.arange(info.num_frames)):
        if frame in shifts:
            x0, y0 = (0, 0) if whole else (int(0.05 * w) + shifts[frame], int(0.1 * h))
            x1, y1 = (w, h) if whole else (x0 + int(0.8 * w), y0 + int(0.85 * h))
            image = image.copy()
            patch = np.roll(texture, shifts[frame], axis=1) if textured else 128
            image[y0:y1, max(0, x0) : x1] = patch if np.isscalar(patch) else patch[y0:y1, max(0, x0) : x1]
            corners[int(frame)] = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
        writer.write(image)
    writer.release()
    return corners


def test_a_subject_hiding_a_tripods_view_does_not_make_it_moving(mixed: list, tmp_path: Path) -> None:
    """A board held close to a tripod (tracked: its corners) hides most of its background in 3 of 12 samples:
    those samples are not evidence either way, and the camera is static. An untracked occluder over the whole
    view in 2 samples leaves them unmeasured: static, and the report says which frames took the static pose
    unseen. The handheld camera with the same board is still moving."""
    close = {4: 0, 5: 30, 6: 60}
    board = _occluded_video(mixed[0].path, tmp_path / "board.mp4", close, textured=True)
    test = measure_motion(probe_video(tmp_path / "board.mp4"), board, 10.0)
    assert test.static and test.hidden == [4, 5, 6] and test.moved is None, (test.reason, test.hidden)
    assert "3 hidden by the tracked subject" in test.reason and test.to_json()["hidden_by_subject"] == [4, 5, 6]

    _occluded_video(mixed[0].path, tmp_path / "covered.mp4", {4: 0, 5: 0}, textured=False, whole=True)
    test = measure_motion(probe_video(tmp_path / "covered.mp4"))
    assert test.static and test.moved is not None, test.reason
    assert "not seen in sampled frames 4, 5" in test.moved and "take the static pose" in test.moved

    board = _occluded_video(mixed[1].path, tmp_path / "handheld.mp4", close, textured=True)
    test = measure_motion(probe_video(tmp_path / "handheld.mp4"), board, 10.0)
    assert not test.static and "moving" in test.reason, test.reason


@pytest.mark.parametrize(
    ("kinds", "static"),
    [
        ("RR", True),  # a two-frame video at rest
        ("RD", True),  # one odd sample
        ("RRRRDD", False),  # displaced twice
        ("RRRRDU", False),  # displaced once, unmeasured once
        ("RRRRRRRRRRRDRRRRRRRRURRR", True),  # the same among many at rest: an arm close to a desk webcam
        ("RRRRRRRRUURRRRRR", True),  # a person passing close to a tripod: the background comes back
        ("RRRRRRRRRRRRRUUU", False),  # the last samples lost: carried off or turned away
        ("UUURRRRRRRRRRRRR", False),  # the same at the start
        ("RRRRRRRUUUUUURRR", False),  # over a third unmeasured
        ("HHHHHHHHHHHHHHHHHHHHRRRD", True),  # hidden samples are no evidence; one odd sample
        ("HHHHHHHHHHHHHHHHHHHHHHRR", False),  # the subject hides nearly every sample: cannot tell
    ],
)
def test_motion_decision_rules(kinds: str, static: bool) -> None:
    """The decision from what each sample measured: R at rest, D displaced, U unmeasured, H hidden by the tracked
    subject (`sfm.static._decide`)."""
    from sfm.static import _decide

    names = {"R": "rest", "D": "displaced", "U": "unmeasured", "H": "hidden"}
    samples = [names[k] for k in kinds]
    shifts = [10.0 if k == "D" else 0.1 for k in kinds]
    tracked = [0.05 if k == "U" else 0.9 for k in kinds]
    decided, reason = _decide(samples, np.arange(len(kinds)), shifts, tracked, 100, 3.0)
    assert decided is static, reason


def test_sample_kinds() -> None:
    """A measured displacement counts where the subject hides most corners; an infinite shift with the corners
    tracked (no rigid group) is displaced, as it was before the subject was known, unless hidden."""
    from sfm.static import _sample_kinds

    shifts = np.array([0.1, 9.0, np.inf, np.inf, 9.0, np.inf, 0.1])
    tracked = np.array([0.9, 0.9, 0.9, 0.9, 0.9, 0.1, 0.1])
    hidden = np.array([False, False, False, True, True, False, True])
    assert _sample_kinds(shifts, tracked, hidden, 3.0) == [
        "rest",
        "displaced",
        "displaced",
        "hidden",
        "displaced",
        "unmeasured",
        "hidden",
    ]
    # displaced in two samples that lost half the corners the others track, the rest at the same place: an arm
    # passing close to a desk webcam (AlternateMoCap's cam 3), not the camera moving
    shifts = np.array([0.1, 0.4, 6.1, 5.9, 0.2, 0.3])
    tracked = np.array([0.8, 0.8, 0.42, 0.4, 0.8, 0.78])
    kinds = _sample_kinds(shifts, tracked, np.zeros(6, bool), 3.8)
    assert kinds == ["rest", "rest", "unmeasured", "unmeasured", "rest", "rest"]
    # the same displacement with the corners tracked as well as at rest: the camera moved
    assert _sample_kinds(shifts, np.full(6, 0.8), np.zeros(6, bool), 3.8)[2:4] == ["displaced", "displaced"]
    # corners lost in the last samples, or in three in a row: moved for good (a knock at the end), not an arm
    end = _sample_kinds(np.array([0.1, 0.2, 0.1, 0.3, 80.0, 82.0]), tracked[[0, 1, 4, 5, 2, 3]], np.zeros(6, bool), 3.8)
    assert end[4:] == ["displaced", "displaced"]
    run = _sample_kinds(
        np.array([0.1, 6.0, 6.1, 5.9, 0.2, 0.3]), np.array([0.8, 0.4, 0.4, 0.4, 0.8, 0.8]), np.zeros(6, bool), 3.8
    )
    assert run[1:4] == ["displaced"] * 3


def test_a_person_walking_away_from_a_tripod_at_the_start_leaves_it_static(mixed: list, tmp_path: Path) -> None:
    """The operator's body fills most of a desk webcam's view in the first samples as they walk to their place
    (caliscope's port_1: 1 %, 1 % and 16 % of the corners tracked): the corners still seen sit where the camera
    rests, so those samples are at rest, partly hidden, not a camera carried off at the start."""
    info = probe_video(mixed[0].path)
    path = tmp_path / "walking_away.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (info.width, info.height))
    covered = {0: 1.0, 1: 0.9, 2: 0.8}  # share of the width the body covers, from the left
    for frame, image in read_frames(info.path, np.arange(info.num_frames)):
        if frame in covered:
            image = image.copy()
            image[:, : int(covered[frame] * info.width)] = 90
        writer.write(image)
    writer.release()
    test = measure_motion(probe_video(path))
    assert test.tracked[1] < 0.2 and test.tracked[2] < 0.2, test.tracked  # too few a share to measure
    assert test.static, test.reason
    # the same corners displaced: a camera carried to its place, moving
    writer = cv2.VideoWriter(
        str(tmp_path / "carried.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (info.width, info.height)
    )
    move = np.float32([[1, 0, 25.0], [0, 1, 10.0]])
    for frame, image in read_frames(info.path, np.arange(info.num_frames)):
        if frame in covered:
            image = cv2.warpAffine(image, move, (info.width, info.height))
            image[:, : int(covered[frame] * info.width)] = 90
        writer.write(image)
    writer.release()
    assert not measure_motion(probe_video(tmp_path / "carried.mp4")).static
