"""Linking a multi-person detector's people through the frames (tracking/people.py) and importing one person or
every person from OpenPose JSON."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from dynrecon.errors import InputError
from tracking.importing import ImportOptions, run_import
from tracking.people import MAX_GAP, link_people
from tracking.tracks import read_tracks

K = 25


def _pose(centre: tuple[float, float], seen: int = K, size: float = 100.0) -> np.ndarray:
    """(K, 3): keypoints on a vertical line of `size` px through `centre`, the first `seen` confident."""
    y = np.linspace(-size / 2, size / 2, K)
    pose = np.c_[np.full(K, centre[0]), centre[1] + y, np.zeros(K)]
    pose[:seen, 2] = 0.9
    pose[seen:, :] = 0.0
    return pose


def test_people_crossing_keep_their_identities() -> None:
    # two people walking towards each other across the image, listed in a different order every frame
    frames = []
    for f in range(40):
        a, b = _pose((100.0 + 10 * f, 300.0)), _pose((500.0 - 10 * f, 320.0), seen=20)
        frames.append((f, [a, b] if f % 3 else [b, a]))
    ids, people = link_people(frames)
    assert [p.frames for p in people] == [40, 40]
    for f, (_, poses) in enumerate(frames):
        # person 0 (most keypoints seen) is the one walking right
        assert ids[f][[p[0, 0] for p in poses].index(100.0 + 10 * f)] == 0


def test_gaps_jumps_and_stale_identities() -> None:
    frames = [(f, [_pose((200.0 + 2 * f, 300.0))]) for f in range(10)]
    frames += [(f, [_pose((200.0 + 2 * f, 300.0))]) for f in range(15, 20)]  # unseen for 5 frames: the same person
    frames += [(20, [_pose((900.0, 300.0))])]  # 7 body sizes away in one frame: someone else
    gap = 20 + MAX_GAP + 1
    frames += [(gap, [_pose((240.0, 300.0))])]  # back after more than MAX_GAP frames: a new identity
    ids, _ = link_people(frames)
    assert [i[0] for i in ids[:15]] == [0] * 15
    assert ids[15][0] != 0 and ids[16][0] not in (0, ids[15][0])
    # an identity seen two frames ago must not take the pose of one seen in the frame before
    frames = [(0, [_pose((100.0, 300.0)), _pose((104.0, 300.0), seen=12)]), (1, [_pose((102.0, 300.0))])]
    frames += [(2, [_pose((103.0, 300.0))])]
    ids, _ = link_people(frames)
    assert ids[1][0] == ids[0][0] == ids[2][0]
    # a frame where the detector found two keypoints of the person: still the same person, before and after
    frames = [(f, [_pose((100.0 + 2 * f, 300.0), seen=2 if f == 10 else K)]) for f in range(40)]
    ids, people = link_people(frames)
    assert [p.frames for p in people] == [40]


def _write_frames(folder: Path, frames: list[list[np.ndarray | None]]) -> None:
    folder.mkdir()
    for f, people in enumerate(frames):
        entries = [{"pose_keypoints_2d": [] if p is None else [float(v) for v in p.ravel()]} for p in people]
        (folder / f"{folder.name[:-5]}_{f:012d}_keypoints.json").write_text(json.dumps({"people": entries}))


def test_openpose_import_follows_one_person(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    frames: list[list[np.ndarray | None]] = []
    for f in range(12):
        a, b = _pose((100.0 + f, 300.0)), _pose((600.0, 300.0 - f), seen=20)
        people: list[np.ndarray | None] = [a, b] if f % 2 else [b, a]
        if f == 3:
            people.insert(0, None)  # a face without a body: an empty pose
        frames.append(people)
    _write_frames(tmp_path / "cam1_json", frames)
    with caplog.at_level(logging.WARNING):
        out = run_import([tmp_path / "cam1_json"], tmp_path / "a.csv", ImportOptions())
    assert "2 people linked through the frames" in caplog.text
    tracks = read_tracks(out)
    nose = np.asarray(tracks.point) == "Nose"
    assert sorted(tracks.frame[nose]) == list(range(12))
    np.testing.assert_array_equal(tracks.xy[nose][np.argsort(tracks.frame[nose]), 0], 100.0 + np.arange(12))
    tracks = read_tracks(run_import([tmp_path / "cam1_json"], tmp_path / "b.csv", ImportOptions(person=1)))
    assert set(tracks.xy[:, 0]) == {600.0} and len(set(tracks.point)) == 20
    tracks = read_tracks(run_import([tmp_path / "cam1_json"], tmp_path / "c.csv", ImportOptions(every_person=True)))
    assert {p.split("_")[0] for p in tracks.point} == {"person0", "person1"} and len(tracks) == 12 * 45
    with pytest.raises(InputError, match="--person 2: only 2 people"):
        run_import([tmp_path / "cam1_json"], tmp_path / "d.csv", ImportOptions(person=2))


DATA = Path(__file__).resolve().parents[1] / "data" / "pose2sim_multi" / "openpose_people.jsonl"


def _reprojection_px(cameras: list, uv: np.ndarray) -> np.ndarray:
    """uv: (C, N, 2) with NaN -> per observation of points seen in 3+ views, the reprojection error (px) of the
    linear triangulation from all its views."""
    import cv2

    rays = [
        cv2.undistortPoints(np.nan_to_num(uv[c]).reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
        for c, cam in enumerate(cameras)
    ]
    errors = []
    for n in range(uv.shape[1]):
        views = [c for c in range(len(cameras)) if np.isfinite(uv[c, n, 0])]
        if len(views) < 3:
            continue
        rows = []
        for c in views:
            P = np.c_[cameras[c].R, cameras[c].t]
            rows += [rays[c][n, 0] * P[2] - P[0], rays[c][n, 1] * P[2] - P[1]]
        X = np.linalg.svd(np.array(rows))[2][-1]
        X = X[:3] / X[3]
        for c in views:
            cam = cameras[c]
            p = cv2.projectPoints(X.reshape(1, 3), cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)[0].reshape(2)
            errors.append(float(np.linalg.norm(p - uv[c, n])))
    return np.array(errors)


@pytest.mark.shared
def test_pose2sim_multi_person_detections_follow_one_participant(shared_dir: Path, tmp_path: Path) -> None:
    """Pose2Sim's raw OpenPose output of its two-participant trial (2-3 people per frame, listed in a different
    order every frame): the imported person is one participant in every frame and every view, which the lab
    calibration checks; people[0] of each frame (what the importer took before) mixes them."""
    from sfm.calibration import read_calibration

    lines = [json.loads(line) for line in DATA.read_text().splitlines()]
    first: dict[tuple[int, int], np.ndarray] = {}  # (camera, frame) -> people[0]'s pose
    for line in lines:
        path = tmp_path / line["file"]
        path.parent.mkdir(exist_ok=True)
        path.write_text(json.dumps({"people": line["people"]}))
        camera, frame = int(line["file"][4]) - 1, int(Path(line["file"]).stem.split(".")[-1])
        if line["people"] and line["people"][0]["pose_keypoints_2d"]:
            first[camera, frame] = np.array(line["people"][0]["pose_keypoints_2d"]).reshape(-1, 3)
    out = tmp_path / "tracks.csv"
    for c in range(1, 5):
        run_import([tmp_path / f"cam0{c}_json"], out, ImportOptions(video=f"cam0{c}", min_score=0.3))
    tracks = read_tracks(out)
    names = sorted(set(tracks.point))
    uv = np.full((4, 100 * len(names), 2), np.nan)
    for i in range(len(tracks)):
        uv[int(tracks.video[i][-1]) - 1, int(tracks.frame[i]) * len(names) + names.index(tracks.point[i])] = tracks.xy[
            i
        ]
    before = np.full((4, 100 * 25, 2), np.nan)
    for (c, f), pose in first.items():
        seen = pose[:, 2] >= 0.3
        before[c, f * 25 : (f + 1) * 25][seen] = pose[seen, :2]
    cameras = read_calibration(shared_dir / "data" / "videos" / "pose2sim_demo" / "calibration" / "Calib.qca.txt")
    now, then = _reprojection_px(cameras, uv), _reprojection_px(cameras, before)
    # measured: 13 / 25 px (median / p90; OpenPose on 1920 px frames) against 143 / 342 px for people[0]
    assert len(now) > 8000 and np.median(now) < 20.0 and np.percentile(now, 90) < 40.0, np.percentile(now, [50, 90])
    assert np.median(then) > 5 * np.median(now)


def test_person_option_on_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from dynrecon.cli import main

    _write_frames(tmp_path / "cam1_json", [[_pose((100.0, 300.0)), _pose((400.0, 300.0), seen=20)]] * 3)
    assert (
        main(["import-tracks", str(tmp_path / "cam1_json"), "--person", "all", "--out", str(tmp_path / "a.csv")]) == 0
    )
    assert {p.split("_")[0] for p in read_tracks(tmp_path / "a.csv").point} == {"person0", "person1"}
    assert main(["import-tracks", str(tmp_path / "cam1_json"), "--person", "1", "--out", str(tmp_path / "b.csv")]) == 0
    assert len(set(read_tracks(tmp_path / "b.csv").point)) == 20
    assert main(["import-tracks", str(tmp_path / "cam1_json"), "--person", "-1", "--out", str(tmp_path / "c.csv")]) == 2
    assert "--person -1: expected a number 0, 1, ... or all" in capsys.readouterr().err


def test_person_is_for_openpose_and_dlc_only(tmp_path: Path) -> None:
    plain = tmp_path / "plain.csv"
    plain.write_text("video,frame,point,x,y\ncam1,0,nose,1,2\n")
    with pytest.raises(InputError, match="--person applies to OpenPose JSON, DeepLabCut and SLEAP files, not to csv"):
        run_import([plain], tmp_path / "out.csv", ImportOptions(every_person=True))
    assert len(read_tracks(run_import([plain], tmp_path / "out.csv", ImportOptions()))) == 1
