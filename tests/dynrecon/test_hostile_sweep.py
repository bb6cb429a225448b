"""Hostile input found by a sweep of every command (2026-11-28): each case exits 2 with one line naming the file
(and the line, frame or option) and what to do, where it used to raise a traceback or write a silently wrong result."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from synthetic_motion import simulated_phones

from dynrecon.cli import main
from dynrecon.errors import InputError
from sfm.calibration import read_calibration


@pytest.fixture(scope="module")
def phones(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_phones(tmp_path_factory.mktemp("phones"))


def _edited(phones: Path, folder: Path, edit) -> Path:
    document = json.loads((phones / "cameras.json").read_text())
    edit(document["videos"])
    path = folder / "cameras.json"
    path.write_text(json.dumps(document))
    return path


def _solve(cameras: Path, tracks: Path, out: Path, *extra: str) -> int:
    return main(
        ["solve", "--cameras", str(cameras), "--tracks", str(tracks), "--out", str(out), "--no-recording", *extra]
    )


def _one_line(capsys: pytest.CaptureFixture[str], status: int, *words: str) -> str:
    err = capsys.readouterr().err
    assert status == 2, err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 1, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def _set_times(videos: list, name: str, times) -> None:
    video = next(v for v in videos if v["name"] == name)
    for frame, time in zip(video["frames"], times(len(video["frames"])), strict=True):
        frame["time"] = time


TIMES = {
    "all equal": (lambda n: [0.0] * n, "is not after frame 0's"),
    "reversed": (lambda n: [-i / 30 for i in range(n)], "is not after frame 0's"),
    "milliseconds": (lambda n: [1000 * i / 30 for i in range(n)], "times the"),
    "1e300": (lambda n: [i / 30 for i in range(n - 1)] + [1e300], "implausible"),
}


@pytest.mark.parametrize("case", list(TIMES), ids=list(TIMES))
def test_decoder_times_that_are_not_seconds_from_the_start(
    phones: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    times, words = TIMES[case]
    first = json.loads((phones / "cameras.json").read_text())["videos"][0]["name"]
    cameras = _edited(phones, tmp_path, lambda videos: _set_times(videos, first, times))
    line = _one_line(capsys, _solve(cameras, phones / "tracks.csv", tmp_path / "out"), str(cameras), words)
    assert f"video {first!r}" in line
    assert not (tmp_path / "out" / "points3d.csv").exists()


def test_a_huge_clock_offset(phones: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cameras = _edited(phones, tmp_path, lambda videos: videos[1].update(clock_offset=1e300))
    _one_line(capsys, _solve(cameras, phones / "tracks.csv", tmp_path / "out"), str(cameras), '"clock_offset"')


def test_one_pose_copied_to_every_video(phones: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def copy(videos: list) -> None:
        pose = {key: videos[0]["frames"][0][key] for key in ("R", "t")}
        for video in videos:
            for frame in video["frames"]:
                frame.update(pose)

    cameras = _edited(phones, tmp_path, copy)
    _one_line(capsys, _solve(cameras, phones / "tracks.csv", tmp_path / "out"), str(cameras), "no baseline")


def test_one_posed_frame_per_video_solves(phones: Path, tmp_path: Path) -> None:
    """Videos of one frame each have no frame period: the clock search skips them instead of failing."""
    cameras = _edited(phones, tmp_path, lambda videos: [v.update(frames=v["frames"][:1]) for v in videos])
    assert _solve(cameras, phones / "tracks.csv", tmp_path / "out") == 0


def test_soft_rays_without_weight(phones: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = _solve(phones / "cameras.json", phones / "tracks.csv", tmp_path / "out", "--lambda3", "0")
    _one_line(capsys, status, "--lambda3 0", "--constraint hard")


def test_an_empty_output_path(phones: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        _solve(phones / "cameras.json", phones / "tracks.csv", "")
    assert exit_info.value.code == 2
    assert "--out: must not be empty" in capsys.readouterr().err


def test_a_negative_seed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = main(["simulate", "--mode", "flight", "--duration", "1", "--seed", "-1", "--out", str(tmp_path)])
    _one_line(capsys, status, "--seed -1")


TRACKS_HEADERS = {
    "semicolons": ("video;frame;point;x;y\ncam0;0;m0;1;2\n", "separated by ';'"),
    "tabs": ("video\tframe\tpoint\tx\ty\ncam0\t0\tm0\t1\t2\n", "separated by '\\t'"),
    "upper case": ("Video,Frame,Point,X,Y\ncam0,0,m0,1,2\n", "lower case"),
    "a column twice": ("video,frame,point,x,y,x\ncam0,0,m0,1,2,3\n", "column 'x' appears twice"),
    "only a header": ("video,frame,point,x,y\n", "only a header"),
}


@pytest.mark.parametrize("case", list(TRACKS_HEADERS), ids=list(TRACKS_HEADERS))
def test_tracks_csv_headers(phones: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    text, words = TRACKS_HEADERS[case]
    tracks = tmp_path / "tracks.csv"
    tracks.write_text(text)
    _one_line(capsys, _solve(phones / "cameras.json", tracks, tmp_path / "out"), str(tracks), words)


def test_cameras_json_with_a_byte_order_mark_reads(phones: Path, tmp_path: Path) -> None:
    cameras = tmp_path / "cameras.json"
    cameras.write_bytes(b"\xef\xbb\xbf" + (phones / "cameras.json").read_bytes())
    assert _solve(cameras, phones / "tracks.csv", tmp_path / "out") == 0


def test_an_infinite_coordinate_in_deeplabcut_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dlc = tmp_path / "camADLC_resnet50_demo.csv"
    dlc.write_text("scorer,me,me,me\nbodyparts,snout,snout,snout\ncoords,x,y,likelihood\n0,10,20,0.9\n1,inf,21,0.9\n")
    status = main(["import-tracks", str(dlc), "--out", str(tmp_path / "tracks.csv")])
    _one_line(capsys, status, str(dlc), "line 5", "'inf'")


def test_deeplabcut_output_saved_with_a_byte_order_mark_is_recognized(tmp_path: Path) -> None:
    """A spreadsheet's byte-order mark before DLC's `scorer` row: still DeepLabCut, not a CSV lacking columns."""
    from tracking.tracks import read_tracks

    dlc = tmp_path / "camADLC_resnet50_demo.csv"
    text = "scorer,me,me,me\nbodyparts,snout,snout,snout\ncoords,x,y,likelihood\n0,10,20,0.9\n1,11,21,0.8\n"
    dlc.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert main(["import-tracks", str(dlc), "--video", "camA", "--out", str(tmp_path / "tracks.csv")]) == 0
    tracks = read_tracks(tmp_path / "tracks.csv")
    assert tracks.point_names() == ["snout"] and tracks.xy.tolist() == [[10.0, 20.0], [11.0, 21.0]]


def test_two_calibrated_cameras_of_one_name(tmp_path: Path) -> None:
    table = (
        '[{key}]\nname = "cam01"\nsize = [100, 100]\n'
        "matrix = [[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]]\n"
        "distortions = [0.0, 0.0, 0.0, 0.0]\nrotation = [0.0, 0.0, 0.0]\ntranslation = [{x}, 0.0, 0.0]\n"
    )
    path = tmp_path / "calib.toml"
    path.write_text(table.format(key="cam_1", x=0.0) + table.format(key="cam_2", x=1.0))
    with pytest.raises(InputError, match="two cameras are named 'cam01'"):
        read_calibration(path)


def test_times_off_the_fps_but_not_milliseconds_are_warned_and_kept(
    phones: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A timelapse's real capture times (1 s per frame in a 30 fps file) are not an error; milliseconds are."""
    from sfm.cameras import read_cameras

    def timelapse(videos: list) -> None:
        videos[0]["fps"] = 30.0
        _set_times(videos, videos[0]["name"], lambda n: [float(i) for i in range(n)])

    path = _edited(phones, tmp_path, timelapse)
    cameras = read_cameras(path)
    assert [f.time for f in cameras.videos[0].frames][:3] == [0.0, 1.0, 2.0]
    read_cameras(path)  # several steps of one run read the file: the warning is said once
    said = [r for r in caplog.records if "times the" in r.getMessage() and "used as given" in r.getMessage()]
    assert len(said) == 1 and str(path) in said[0].getMessage()


def test_a_deeplabcut_image_name_without_a_number(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The frame comes from the image's name, never from a number in its folder's (a date)."""
    dlc = tmp_path / "camADLC_resnet50_demo.csv"
    dlc.write_text(
        "scorer,,,me,me\nbodyparts,,,snout,snout\ncoords,,,x,y\nlabeled-data,PrL-19_11042020,imgABC.png,10,20\n"
    )
    status = main(["import-tracks", str(dlc), "--out", str(tmp_path / "tracks.csv")])
    _one_line(capsys, status, str(dlc), "line 4", "'imgABC.png'")


def test_importing_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "detections.csv"
    empty.write_text("video,frame,point,x,y\n")
    status = main(["import-tracks", str(empty), "--out", str(tmp_path / "tracks.csv")])
    _one_line(capsys, status, str(empty), "no detection to import")
    assert not (tmp_path / "tracks.csv").exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["solve", "--lambda2", "1e300"], "--lambda2 1e+300 must be a number from 0 to"),
        (["simulate", "--distance", "0"], "--distance 0.0"),
        (["import-calibration", "--offsets", "cam01=1e300"], "clock offsets are seconds below"),
        (["register", "--threads", "0"], "--threads 0"),
        (["run", "--track-window", "3"], "--track-window 3: must be 5 to"),
    ],
    ids=["lambda", "distance", "offsets", "threads", "track-window"],
)
def test_options_out_of_range(
    phones: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], words: str
) -> None:
    command, *flags = argv
    video = tmp_path / "cam01.mp4"
    video.write_bytes(b"")  # never opened: the options are checked first
    rest = {
        "solve": ["--cameras", str(phones / "cameras.json"), "--tracks", str(phones / "tracks.csv")],
        "simulate": [str(phones.parent / "motion.trc"), "--mode", "phones"],
        "import-calibration": [str(tmp_path / "calib.toml"), str(video)],
        "register": [str(video), str(video)],
        "run": [str(video), str(video)],
    }[command]
    try:
        status = main([command, *rest, *flags, "--out", str(tmp_path / "out")])
    except SystemExit as exit_info:  # argparse's own error: exit 2 with its usage line
        status = int(exit_info.code or 0)
        err = capsys.readouterr().err
        assert status == 2 and words in err, err
        return
    _one_line(capsys, status, words)


@pytest.mark.parametrize(
    "rows, words",
    [
        ("cam0,0,p,1,2,3,1\ncam0,0,p,1,2,4,1\n", "also on line 2"),
        ("cam0,0,p,inf,2,3,1\n", "not finite"),
        ("cam0,0,p,1e300,2,3,1\n", "implausible"),
        ("cam0,0,p,1,2\n", "line 2: expected 7 fields, found 5"),
        ("cam0,0,p,abc,2,3,1\n", "line 2: x 'abc' is not a number"),
        ("cam0,0,p,1,,,1\n", "line 2: x, y, z are partly empty"),
        ("cam0,0,p,1,2,3,yes\n", "line 2: observed is 'yes'"),
    ],
    ids=["a row twice", "inf", "1e300", "short", "not a number", "partly empty", "observed yes"],
)
def test_points_csv_rows_that_are_not_one_position(tmp_path: Path, rows: str, words: str) -> None:
    from reconstruct.outputs.points import read_points

    path = tmp_path / "points3d.csv"
    path.write_text("video,frame,point,x,y,z,observed\n" + rows)
    with pytest.raises(InputError, match=words):
        read_points(path)


def test_two_static_videos_at_one_pose_are_warned(phones: Path, caplog: pytest.LogCaptureFixture) -> None:
    from reconstruct.inputs import build_problem_checked
    from sfm.cameras import read_cameras
    from tracking.tracks import read_tracks

    cameras = read_cameras(phones / "cameras.json")
    first, second = cameras.videos[:2]
    for frame in second.frames:
        frame.R, frame.t = first.frames[0].R.copy(), first.frames[0].t.copy()
    build_problem_checked(cameras, read_tracks(phones / "tracks.csv"))
    assert any(
        f"videos {first.name!r} and {second.name!r} have their camera at the same point" in r.getMessage()
        for r in caplog.records
    )


def test_a_calibration_table_without_its_matrix_is_warned(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "calib.toml"
    path.write_text(
        '[cam_1]\nname = "cam01"\nsize = [100, 100]\nmatrix = [[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, '
        '1.0]]\nrotation = [0.0, 0.0, 0.0]\ntranslation = [0.0, 0.0, 0.0]\n\n[cam_2]\nname = "cam02"\nsize = [100, '
        "100]\nrotation = [0.0, 0.0, 0.0]\ntranslation = [1.0, 0.0, 0.0]\n"
    )
    assert [camera.name for camera in read_calibration(path)] == ["cam01"]
    assert any("[cam_2] has no intrinsics" in r.getMessage() for r in caplog.records)


def test_a_frame_given_twice_is_named_before_its_time(phones: Path, tmp_path: Path) -> None:
    from sfm.cameras import read_cameras

    cameras = _edited(phones, tmp_path, lambda videos: videos[0]["frames"].append(videos[0]["frames"][1]))
    with pytest.raises(InputError, match="frame appears twice"):
        read_cameras(cameras)


@pytest.mark.parametrize("nominal, expected", [(30.0, 30.0), (29.97, 29.97), (1000.0, None), (90000.0, None)])
def test_a_container_rate_the_timestamps_contradict_is_not_written(nominal: float, expected: float | None) -> None:
    """OpenCV reports 1000 fps for browser WebM and 90000 for some IP cameras whose frames are 1/30 s apart:
    cameras.json's fps is then null (the times carry the truth), not a rate the solve would refuse."""
    import numpy as np

    from sfm.video import ProbedVideo

    video = ProbedVideo(
        path=Path("v.webm"), name="v", width=64, height=48, times=np.arange(30) / 30, nominal_fps=nominal
    )
    assert video.fps == expected


def test_a_skeleton_without_points_is_refused(tmp_path: Path) -> None:
    from labeling.skeleton import read_skeleton

    path = tmp_path / "skeleton.json"
    path.write_text('{"bones": [["a", "b"]]}')
    with pytest.raises(InputError, match="no 'points' or 'connections'"):
        read_skeleton(path)


def test_intrinsics_for_only_some_videos_name_the_others(phones: Path, caplog: pytest.LogCaptureFixture) -> None:
    import numpy as np

    from sfm.cameras import read_cameras
    from sfm.intrinsics import known_intrinsics
    from sfm.video import ProbedVideo

    video = read_cameras(phones / "cameras.json").videos[0]
    infos = [
        ProbedVideo(
            path=Path(f"{name}.mp4"),
            name=name,
            width=video.width,
            height=video.height,
            times=np.arange(5) / 30,
            nominal_fps=30.0,
        )
        for name in (video.name, "elsewhere")
    ]
    assert list(known_intrinsics(phones / "cameras.json", infos)) == [video.name]
    assert any("gives no intrinsics for elsewhere" in r.getMessage() for r in caplog.records)


def test_one_video_under_two_names_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A copy (or a link) of one camera's video under another name would be a second camera with no baseline."""
    sample = Path(__file__).resolve().parents[2] / "data_samples" / "video_sample"
    copy = tmp_path / "cam9.mp4"
    copy.write_bytes((sample / "cam1.mp4").read_bytes())
    args = ["register", str(sample / "cam0.mp4"), str(sample / "cam1.mp4"), str(copy), "--out", str(tmp_path / "ws")]
    _one_line(capsys, main(args), str(copy), "same contents as", "cam1.mp4", "once")
    assert not (tmp_path / "ws" / "cameras.json").exists()


def test_board_options_given_the_wrong_kind_of_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A folder where --board wants videos, and a video where --board wants the board's description."""
    sample = Path(__file__).resolve().parents[2] / "data_samples" / "video_sample"
    board = tmp_path / "charuco.toml"
    board.write_text('columns = 4\nrows = 5\nsquare_size_override_cm = 5.4\ndictionary = "DICT_4X4_1000"\n')
    status = main(["import-tracks", str(sample), "--board", str(board), "--out", str(tmp_path / "t.csv")])
    _one_line(capsys, status, str(sample), "is a folder", "video files")
    videos = [str(sample / "cam0.mp4"), str(sample / "cam1.mp4")]
    status = main(["register", *videos, "--board", str(sample / "cam2.mp4"), "--out", str(tmp_path / "ws")])
    _one_line(capsys, status, "cam2.mp4", "is a video, not a board description", "charuco.toml")
    assert not (tmp_path / "t.csv").exists() and not (tmp_path / "ws" / "cameras.json").exists()
