"""`dynrecon run` when the background cannot pose static videos: the `subject` stage registers again after
tracking, with the subject's tracks, and the later stages use its cameras.

The two registrations are stand-ins here (the real ones are tested in tests/sfm and tests/integration): the first
raises RegistrationError as `register` does on a static rig whose views share no background, the second writes the
cameras of a simulated capture, whose tracks the solve then reconstructs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from synthetic_motion import simulated_phones

from dynrecon import pipeline
from dynrecon.errors import DynreconError
from sfm.export import write_ply
from sfm.register_subject import TRACK_ADVICE
from sfm.stage import RegisterOptions, RegistrationError


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three static simulated phones (30, 25, 20 fps) with known clocks."""
    return simulated_phones(tmp_path_factory.mktemp("capture"))


def _subject_only_registration(capture: Path, monkeypatch: pytest.MonkeyPatch) -> list[RegisterOptions]:
    """A stand-in registration: the background fails as on a static rig without shared background, the subject
    stage writes the simulated capture's cameras. Returns the options of every call."""
    calls: list[RegisterOptions] = []

    def register(videos: list[Path], register_dir: Path, options: RegisterOptions) -> None:
        calls.append(options)
        if options.tracks is None:
            raise RegistrationError("only 0 of 3 videos registered (none); cameras.json not written")
        register_dir.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(capture / "cameras.json", register_dir / "cameras.json")
        write_ply(register_dir / "background.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))

    monkeypatch.setattr(pipeline, "_register", register)
    return calls


def test_static_videos_left_out_are_registered_from_the_tracks(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = _subject_only_registration(capture, monkeypatch)
    videos = []
    for name in ("cam0", "cam1", "cam2"):  # the stand-ins never read them; the record stage warns and goes on
        videos.append(tmp_path / f"{name}.mp4")
        videos[-1].write_bytes(b"not a video")
    ws = tmp_path / "ws"
    result = pipeline.run_stages(videos, ws, pipeline.PipelineOptions(tracks=capture / "tracks.csv"))
    ran = [s.name for s in result.stages]
    assert ran == ["subject", "solve", "record", "export"]  # register raised: no stage record
    assert calls[0].tracks is None and calls[1].tracks == ws / "tracks.csv"
    assert (ws / "register_subject" / "cameras.json").is_file() and not (ws / "register" / "cameras.json").exists()
    report = json.loads((ws / "report.json").read_text())
    assert report["inputs"]["cameras"].endswith("register_subject/cameras.json")


def test_without_tracks_the_registration_error_stands(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The error stands, and its advice is `run`'s own (labels in the workspace, --tracks), not register's
    `dynrecon track WS`, which a run's workspace cannot take before it has labels."""
    report = tmp_path / "register_report.json"
    reason = f"the subject path could not pose them: no 2D tracks of the moving subject: {TRACK_ADVICE}"

    def register(videos: list[Path], register_dir: Path, options: RegisterOptions) -> None:
        raise RegistrationError.of("only 0 of 2 videos registered (none)", reason, report)

    monkeypatch.setattr(pipeline, "_register", register)
    videos = [tmp_path / "a.mp4", tmp_path / "b.mp4"]
    for video in videos:
        video.write_bytes(b"x")
    with pytest.raises(RegistrationError) as raised:
        pipeline.run_stages(videos, tmp_path / "ws", pipeline.PipelineOptions())
    message = str(raised.value)
    assert "--tracks FILE" in message and "dynrecon label WS" in message and "dynrecon track WS" not in message
    assert message.startswith("only 0 of 2 videos registered (none)") and message.endswith(f"Details: {report}")


def test_a_static_video_the_background_left_out_triggers_the_subject_stage(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[RegisterOptions] = []

    def register(videos: list[Path], register_dir: Path, options: RegisterOptions) -> None:
        calls.append(options)
        register_dir.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(capture / "cameras.json", register_dir / "cameras.json")
        write_ply(register_dir / "background.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
        left_out = "none" if options.tracks is None else "subject"
        videos_report = [
            {"name": "cam0", "camera": "static", "posed_by": left_out},
            {"name": "cam1", "camera": "moving", "posed_by": "background SfM"},
        ]
        (register_dir / "register_report.json").write_text(json.dumps({"videos": videos_report}))

    monkeypatch.setattr(pipeline, "_register", register)
    videos = [tmp_path / f"cam{i}.mp4" for i in range(3)]
    for video in videos:
        video.write_bytes(b"x")
    result = pipeline.run_stages(videos, tmp_path / "ws", pipeline.PipelineOptions(tracks=capture / "tracks.csv"))
    assert [s.name for s in result.stages] == ["register", "subject", "solve", "record", "export"]
    assert [c.tracks is None for c in calls] == [True, False]


def test_the_board_goes_to_the_subject_stage_and_an_edited_board_reruns_it(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = _subject_only_registration(capture, monkeypatch)
    videos = [tmp_path / f"cam{i}.mp4" for i in range(3)]
    for video in videos:
        video.write_bytes(b"x")
    board = tmp_path / "charuco.toml"
    board.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n')
    options = pipeline.PipelineOptions(tracks=capture / "tracks.csv", register=RegisterOptions(board=board))
    ws = tmp_path / "ws"

    first = pipeline.run_stages(videos, ws, options)
    assert [s.name for s in first.stages] == ["subject", "solve", "record", "export"]
    assert [c.board for c in calls] == [None, board]  # the background stage never reads the board

    calls.clear()
    again = pipeline.run_stages(videos, ws, options)
    assert [s.name for s in again.stages if not s.skipped] == [] and [c.board for c in calls] == [None]

    calls.clear()
    board.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.0\ndictionary = "DICT_4X4_1000"\n')
    edited = pipeline.run_stages(videos, ws, options)
    assert [c.board for c in calls] == [None, board]
    assert "subject" in [s.name for s in edited.stages if not s.skipped]


def test_given_labels_never_overwrite_the_clicks_in_the_workspace(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """WS/labels.csv holds the labeling page's clicks; `run --labels OTHER.csv` keeps them beside the copy."""

    def register(videos: list[Path], register_dir: Path, options: RegisterOptions) -> None:
        raise RegistrationError("only 0 of 3 videos registered (none)")

    monkeypatch.setattr(pipeline, "_register", register)
    ws = tmp_path / "ws"
    ws.mkdir()
    clicks = "video,frame,point,x,y,source\ncam0,99,knee,10,10,label\n"
    (ws / "labels.csv").write_text(clicks)
    other = tmp_path / "other.csv"
    other.write_text("video,frame,point,x,y,source\ncam0,1,knee,12,10,label\n")
    videos = [tmp_path / f"cam{i}.mp4" for i in range(3)]
    for video in videos:
        video.write_bytes(b"x")
    with pytest.raises(DynreconError):  # the stand-in videos cannot be tracked; the labels were copied before
        pipeline.run_stages(videos, ws, pipeline.PipelineOptions(labels=other))
    kept = list(ws.glob("labels.before-*.csv"))
    assert (ws / "labels.csv").read_text() == other.read_text()
    assert len(kept) == 1 and kept[0].read_text() == clicks


def test_tracks_that_number_people_per_video_are_registered_again(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The background posed every video, but the tracks number people per video (`import-tracks --person all`):
    registration runs again with them (it matches the people and writes each video's map), and the solve uses
    the maps; the second person of cam0, matched with nobody, is left out."""
    from sfm.cameras import read_cameras, write_cameras
    from tracking.tracks import Tracks, read_tracks, write_tracks

    plain = read_tracks(capture / "tracks.csv")
    rows = [
        (v, int(f), f"person0_{p}", *map(float, xy))
        for v, f, p, xy in zip(plain.video, plain.frame, plain.point, plain.xy, strict=True)
    ]
    rows += [(v, f, p.replace("person0", "person1"), x + 50, y) for v, f, p, x, y in rows if v == "cam0"]
    write_tracks(tmp_path / "people.csv", Tracks.from_rows(rows))
    calls: list[RegisterOptions] = []

    def register(videos: list[Path], register_dir: Path, options: RegisterOptions) -> None:
        calls.append(options)
        register_dir.mkdir(parents=True, exist_ok=True)
        cameras = read_cameras(capture / "cameras.json")
        for video in cameras.videos:
            video.people = None if options.tracks is None else {0: 0}
        write_cameras(register_dir / "cameras.json", cameras)
        write_ply(register_dir / "background.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
        videos_report = [{"name": v.name, "camera": "static", "posed_by": "background SfM"} for v in cameras.videos]
        (register_dir / "register_report.json").write_text(json.dumps({"videos": videos_report}))

    monkeypatch.setattr(pipeline, "_register", register)
    videos = [tmp_path / f"cam{i}.mp4" for i in range(3)]
    for video in videos:
        video.write_bytes(b"x")
    ws = tmp_path / "ws"
    result = pipeline.run_stages(videos, ws, pipeline.PipelineOptions(tracks=tmp_path / "people.csv"))
    assert [s.name for s in result.stages] == ["register", "subject", "solve", "record", "export"]
    assert [c.tracks is None for c in calls] == [True, False]
    header, *lines = (ws / "points3d.csv").read_text().splitlines()
    points = {line.split(",")[header.split(",").index("point")] for line in lines}
    assert points and all(p.startswith("person0_") for p in points)
