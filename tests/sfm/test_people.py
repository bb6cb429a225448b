"""People numbered per video matched across videos (sfm/subject/people.py), their maps in cameras.json, and the
solve's renumbering (sfm/people.py)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.errors import InputError
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras, write_cameras
from sfm.people import check_people_mapped, per_video_people, renumber_people
from sfm.subject.model import SubjectVideo
from sfm.subject.people import associate_people
from sfm.subject.synthetic import Truth, make_rig, skeleton_motion
from tracking.import_openpose import read_openpose
from tracking.tracks import Tracks


def _project(truth: Truth, motion: np.ndarray, v: int) -> np.ndarray:
    """(F, P, 2) pixels of `motion` (F, P, 3) in camera v."""
    uv, _ = cv2.projectPoints(
        motion.reshape(-1, 3), cv2.Rodrigues(truth.R[v])[0], truth.t[v], truth.K[v], truth.dist[v]
    )
    return uv.reshape(*motion.shape[:2], 2)


def _two_people() -> tuple[Tracks, list[SubjectVideo]]:
    """Three static cameras filming two people walking (and, in cam2, a bystander standing still); each video
    numbers its people its own way."""
    _, videos, truth = make_rig(n_cameras=3, duration=8.0, noise_px=1.0, known_K=False, seed=4)
    numbers = {"cam0": (0, 1), "cam1": (1, 0), "cam2": (0, 2)}  # (the walker, the other one)
    rng = np.random.default_rng(0)
    rows: list[tuple[str, int, str, float, float]] = []
    for v, video in enumerate(videos):
        t = video.times + truth.offsets[v]
        walker = skeleton_motion(t)
        other = skeleton_motion(t + 5.0) + np.array([0.8, -0.6, 0.0])  # another path through the room
        for person, motion in zip(numbers[video.name], (walker, other), strict=True):
            uv = _project(truth, motion, v) + rng.normal(0, 1.0, (*motion.shape[:2], 2))
            for f, p in np.ndindex(*uv.shape[:2]):
                rows.append((video.name, f, f"person{person}_k{p}", *map(float, uv[f, p])))
        if video.name == "cam2":
            for f in range(len(t)):
                for p in range(12):
                    x, y = 200.0 + 3 * p + rng.normal(0, 1.0), 300.0 + 20 * p + rng.normal(0, 1.0)
                    rows.append(("cam2", f, f"person1_k{p}", x, y))
    return Tracks.from_rows(rows), videos


def test_people_are_matched_across_videos() -> None:
    tracks, videos = _two_people()
    assert per_video_people(tracks) == {"cam0": [0, 1], "cam1": [0, 1], "cam2": [0, 1, 2]}
    found = associate_people(tracks, videos)
    assert sorted(found.groups, key=lambda g: g["cam0"]) == [
        {"cam0": 0, "cam1": 1, "cam2": 0},
        {"cam0": 1, "cam1": 0, "cam2": 2},
    ]
    assert found.left_out == {"cam0": [], "cam1": [], "cam2": [1]}  # the bystander: no other video has them
    # the renumbered tracks: one name per person in every video, the bystander left out
    walker = found.maps["cam0"][0]
    renamed = renumber_people(tracks, found.maps)
    names = {(v, p) for v, p in zip(renamed.video, renamed.point, strict=True) if p.endswith("_k3")}
    assert names == {(v, f"person{n}_k3") for v in ("cam0", "cam1", "cam2") for n in (0, 1)}
    assert found.maps["cam1"][1] == walker and found.maps["cam2"] == {0: walker, 2: 1 - walker}
    table = found.to_json()["pairs"][0]
    assert table["videos"] == ["cam0", "cam1"] and np.argmax(table["inliers"][0]) == 1


def test_tracks_without_per_video_people_are_left_alone() -> None:
    tracks = Tracks.from_rows([("a", 0, "person0_Nose", 1.0, 2.0), ("b", 0, "Nose", 1.0, 2.0)])
    assert per_video_people(tracks) is None
    assert renumber_people(tracks, {}) is tracks
    # one person per video, but not the same number: a threshold left another person in b; matched like several
    tracks = Tracks.from_rows([("a", 0, "person0_Nose", 1.0, 2.0), ("b", 0, "person1_Nose", 1.0, 2.0)])
    assert per_video_people(tracks) == {"a": [0], "b": [1]}


def test_renumbering_and_the_cameras_json_map(tmp_path: Path) -> None:
    tracks = Tracks.from_rows(
        [
            ("a", 0, "person0_Nose", 1.0, 2.0),
            ("a", 0, "person1_Nose", 3.0, 4.0),
            ("a", 0, "person2_Nose", 5.0, 6.0),
            ("a", 0, "L_hand", 7.0, 8.0),
            ("b", 0, "person0_Nose", 9.0, 1.0),
        ]
    )
    out = renumber_people(tracks, {"a": {1: 0, 0: 1}})
    assert list(zip(out.video, out.point, strict=True)) == [
        ("a", "person1_Nose"),
        ("a", "person0_Nose"),
        ("a", "L_hand"),  # not a person's point: as it was
        ("b", "person0_Nose"),  # a video without a map: as it was
    ]  # a's person 2 (matched with nobody) is left out
    frame = FrameCamera(frame=0, K=np.eye(3), R=np.eye(3), t=np.zeros(3))
    cameras = CameraSet(videos=[VideoCameras(name="a", width=4, height=4, frames=[frame], people={1: 0, 0: 1})])
    path = write_cameras(tmp_path / "cameras.json", cameras)
    assert json.loads(path.read_text())["videos"][0]["people"] == {"0": 1, "1": 0}
    assert read_cameras(path).videos[0].people == {0: 1, 1: 0}
    document = json.loads(path.read_text())
    for bad, message in (({"x": 1}, "must map person numbers"), ({"0": 1, "1": 1}, "two people of the video")):
        document["videos"][0]["people"] = bad
        path.write_text(json.dumps(document))
        with pytest.raises(InputError, match=message):
            read_cameras(path)


DATA = Path(__file__).resolve().parents[1] / "data" / "pose2sim_multi" / "openpose_people.jsonl"


@pytest.mark.slow
def test_pose2sim_two_participants_are_matched_as_the_lab_calibration_matches_them(tmp_path: Path) -> None:
    """Pose2Sim's raw OpenPose output of its two-participant trial (4 static cameras, bystanders in two views), no
    calibration, no synchronization: the people are matched as Pose2Sim's own association, made with the lab's
    calibration, matches them (its pose-associated/ files): participant 1 is cam01 person 2, cam02 person 2, cam03
    and cam04 person 1; participant 2 is person 0 everywhere; the bystanders (cam01 1, cam02 1) and a one-frame
    fragment (cam01 3) are left out."""
    for line in (json.loads(text) for text in DATA.read_text().splitlines()):
        path = tmp_path / line["file"]
        path.parent.mkdir(exist_ok=True)
        path.write_text(json.dumps({"people": line["people"]}))
    detections = [
        d
        for c in range(1, 5)
        for d in read_openpose(tmp_path / f"cam0{c}_json", f"cam0{c}", every_person=True)
        if d.score is not None and d.score >= 0.3
    ]
    tracks = Tracks.from_rows([(d.video, d.frame, d.point, d.x, d.y) for d in detections])
    times = np.arange(100) / 60.0
    videos = [SubjectVideo(name=f"cam0{c}", width=1088, height=1920, times=times) for c in range(1, 5)]
    found = associate_people(tracks, videos)
    assert found.groups == [
        {"cam01": 2, "cam02": 2, "cam03": 1, "cam04": 1},
        {"cam01": 0, "cam02": 0, "cam03": 0, "cam04": 0},
    ]
    assert found.left_out == {"cam01": [1, 3], "cam02": [1], "cam03": [], "cam04": []}


def test_the_solve_refuses_people_numbered_per_video_without_a_map(tmp_path: Path) -> None:
    from reconstruct.stage import solve

    frame = FrameCamera(frame=0, K=np.eye(3), R=np.eye(3), t=np.zeros(3))
    cameras = CameraSet(videos=[VideoCameras(name=n, width=4, height=4, frames=[frame]) for n in ("a", "b")])
    rows = [(v, 0, f"person{p}_Nose", 1.0, 2.0) for v in ("a", "b") for p in (0, 1)]
    tracks = Tracks.from_rows(rows)
    tracks.path = tmp_path / "tracks.csv"
    with pytest.raises(InputError, match=r"tracks\.csv: the tracks number people per video .* which person of a, b"):
        solve(cameras, tracks)
    check_people_mapped(cameras, Tracks.from_rows(rows[::2]))  # one person per video: nothing to match


def test_people_on_a_calibrated_rigs_cameras(tmp_path: Path) -> None:
    """A lab's calibration (imported without tracks) gets each video's people map from the tracks, as `register`
    would find it (`dynrecon run --calibration` with tracks that number people per video)."""
    from synthetic_motion import simulated_phones

    from sfm.register_people import people_on_cameras
    from tracking.tracks import read_tracks

    capture = simulated_phones(tmp_path / "capture")
    plain = read_tracks(capture / "tracks.csv")
    names = sorted(set(plain.point))
    numbers = {"cam0": (0, 1), "cam1": (1, 0), "cam2": (0, 1)}  # each video numbers the two halves its own way
    rows = []
    for v, f, p, xy in zip(plain.video, plain.frame, plain.point, plain.xy, strict=True):
        half, k = divmod(names.index(p), len(names) // 2)
        rows.append((v, int(f), f"person{numbers[v][half]}_k{k}", float(xy[0]), float(xy[1])))
    path = people_on_cameras(capture / "cameras.json", Tracks.from_rows(rows), [], tmp_path)
    maps = {v.name: v.people for v in read_cameras(path).videos}
    assert maps["cam0"] == {0: maps["cam2"][0], 1: maps["cam2"][1]} and sorted(maps["cam0"].values()) == [0, 1]
    assert maps["cam1"] == {1: maps["cam0"][0], 0: maps["cam0"][1]}
