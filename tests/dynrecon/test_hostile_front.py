"""Bad input at the front half (register, import-calibration, import-tracks, boards), found by a review that ran the
CLI on crafted files: each is exit status 2 and one line, and nothing the user had is lost."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon.cli import main
from sfm.calibration import StaticCamera, write_toml


def _video(path: Path, frames: int) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (320, 240))
    rng = np.random.default_rng(sum(path.stem.encode()))  # another picture per name: identical files are refused
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8))
    writer.release()
    return path


def _one_line_error(capsys: pytest.CaptureFixture[str], status: int, *words: str) -> None:
    err = capsys.readouterr().err
    lines = [line for line in err.strip().splitlines() if "error:" in line]  # not the progress bars
    assert status == 2 and len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], lines[0]


def _videos(folder: Path, names: tuple[str, ...] = ("cam_0", "cam_1")) -> list[str]:
    return [str(_video(folder / f"{name}.avi", frames=3)) for name in names]


def _calibration(path: Path, names: list[str]) -> Path:
    cameras = [
        StaticCamera(
            name=name,
            width=320,
            height=240,
            K=np.array([[300.0 + i, 0, 160], [0, 300.0 + i, 120], [0, 0, 1]]),
            dist=np.zeros(4),
            R=np.eye(3),
            t=np.array([float(i), 0, 0]),
        )
        for i, name in enumerate(names)
    ]
    return write_toml(path, cameras)


def test_a_register_typo_keeps_the_last_results(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "cameras.json").write_text('{"videos": []}')
    (ws / "register_report.json").write_text("{}")
    videos = _videos(tmp_path)
    for extra in (["--tracks", str(tmp_path / "typo.csv")], ["--intrinsics", str(tmp_path / "typo.toml")]):
        status = main(["-q", "register", *videos, "--out", str(ws), *extra])
        _one_line_error(capsys, status, "typo", "not found")
        assert (ws / "cameras.json").read_text() == '{"videos": []}' and (ws / "register_report.json").exists()


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--scale", "a,a,0.5"], ["--scale", "two different points"]),
        (["--scale", "a,b,1e-300"], ["--scale", "two different points"]),
        (["--keyframes", "-1"], ["--keyframes -1"]),
        (["--time-step", "nan"], ["--time-step nan"]),
        (["--max-frames", "-1"], ["--max-frames -1"]),
        (["--max-ratio", "nan"], ["--max-ratio nan"]),
        (["--camera-model", "FOO"], ["--camera-model 'FOO'"]),
    ],
)
def test_register_options_no_registration_can_use(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], words: list[str]
) -> None:
    status = main(["-q", "register", *_videos(tmp_path), "--out", str(tmp_path / "ws"), *flags])
    _one_line_error(capsys, status, *words)


def test_scale_points_missing_from_the_tracks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tracks = tmp_path / "tracks.csv"
    tracks.write_text("video,frame,point,x,y\ncam_0,0,knee,10,10\ncam_1,0,knee,12,10\n")
    args = ["-q", "register", *_videos(tmp_path), "--out", str(tmp_path / "ws"), "--tracks", str(tracks)]
    _one_line_error(capsys, main([*args, "--scale", "knee,ankle,0.4"]), "ankle", "not in the tracks", "knee")


def test_a_long_point_list_in_an_error_says_it_is_cut() -> None:
    """The points named beside a missing --scale point: never cut short without saying so (18 points showed 10)."""
    from dynrecon.errors import InputError
    from sfm.stage import check_scale_points

    points = {f"p{i:02d}" for i in range(40)}
    with pytest.raises(InputError, match=r"points: p00, p01, .*, p29, \.\.\. \(40 in all\)"):
        check_scale_points(("p00", "nose", 0.4), points, None)
    with pytest.raises(InputError, match=r"points: a, b, c\)"):
        check_scale_points(("a", "nose", 0.4), {"a", "b", "c"}, None)


def test_partly_matching_camera_names_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Three of four names match: by file order the matched cameras would go to other videos."""
    calibration = _calibration(tmp_path / "calib.toml", ["cam_0", "cam_1", "one"])
    videos = _videos(tmp_path, ("cam_2", "cam_1", "cam_0"))
    status = main(["-q", "import-calibration", str(calibration), *videos, "--out", str(tmp_path / "ws")])
    _one_line_error(capsys, status, "cam_2 match no camera name", "one")


def test_no_name_matching_goes_by_file_order(tmp_path: Path) -> None:
    calibration = _calibration(tmp_path / "calib.toml", ["left", "right"])
    videos = _videos(tmp_path, ("a", "b"))
    assert main(["-q", "import-calibration", str(calibration), *videos, "--out", str(tmp_path / "ws")]) == 0
    cameras = json.loads((tmp_path / "ws" / "cameras.json").read_text())
    assert [v["frames"][0]["t"][0] for v in cameras["videos"]] == [0.0, 1.0]


@pytest.mark.parametrize("scale", ["0", "-1", "nan"])
def test_import_calibration_scale_must_be_positive(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], scale: str
) -> None:
    calibration = _calibration(tmp_path / "calib.toml", ["cam_0", "cam_1"])
    args = ["-q", "import-calibration", str(calibration), *_videos(tmp_path), "--out", str(tmp_path / "ws")]
    _one_line_error(capsys, main([*args, "--scale", scale]), f"--scale {scale}", "positive")


def test_import_calibration_out_is_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    calibration = _calibration(tmp_path / "calib.toml", ["cam_0", "cam_1"])
    status = main(["-q", "import-calibration", str(calibration), *_videos(tmp_path), "--out", str(calibration)])
    _one_line_error(capsys, status, "calib.toml", "it is a file")


QCA = (
    '<calibration><cameras><camera serial="cam_0"><fov_video left="0" top="0" right="319" bottom="{bottom}"/>'
    '<transform x="0" y="0" z="0" r11="{r11}" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1"/>'
    '<intrinsic focalLengthU="19200" focalLengthV="19200" centerPointU="10240" centerPointV="7680" skew="{skew}" '
    'radialDistortion1="0" radialDistortion2="0" radialDistortion3="0" tangentalDistortion1="0" '
    'tangentalDistortion2="0"/></camera></cameras></calibration>'
)


@pytest.mark.parametrize(
    ("fields", "words"),
    [
        ({"skew": "abc"}, ['"skew"', "not a number"]),
        ({"r11": "nan"}, ['"r11"', "not a finite number"]),
        ({"bottom": "inf"}, ['"bottom"', "not a finite number"]),
    ],
)
def test_hostile_qca_attributes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fields: dict[str, str], words: list[str]
) -> None:
    qca = tmp_path / "calib.qca.txt"
    qca.write_text(QCA.format(**{"bottom": "239", "r11": "1", "skew": "0", **fields}))
    status = main(["-q", "import-calibration", str(qca), *_videos(tmp_path, ("cam_0",)), "--out", str(tmp_path / "ws")])
    _one_line_error(capsys, status, "calib.qca.txt", *words)


@pytest.mark.parametrize(
    ("board", "words"),
    [
        ("columns = 100000\nrows = 100000\nsquare_size_override_cm = 5", ["columns, rows", "from 2 to"]),
        ("columns = 4\nrows = 5\nsquare_size_override_cm = 1e-300", ["square", "not a printable board"]),
        ("columns = 4\nrows = 5\nsquare_size_override_cm = 5\naruco_scale = 1e-300", ["aruco_scale"]),
        ('columns = 4\nrows = 5\nsquare_size_override_cm = 5\ninverted = "false"', ["inverted", "true or false"]),
        ('columns = 30\nrows = 30\nsquare_size_override_cm = 5\ndictionary = "DICT_4X4_50"', ["450 markers"]),
    ],
)
def test_hostile_board_files(tmp_path: Path, capsys: pytest.CaptureFixture[str], board: str, words: list[str]) -> None:
    path = tmp_path / "charuco.toml"
    path.write_text(board + "\n")
    status = main(["-q", "import-tracks", "--board", str(path), *_videos(tmp_path, ("cam_0",)), "--out", "t.csv"])
    _one_line_error(capsys, status, "charuco.toml", *words)


def test_openpose_coordinates_that_are_not_finite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "cam_0_json"
    folder.mkdir()
    person = {"pose_keypoints_2d": [float("nan"), 1.0, 0.9] + [0.0] * 72}
    (folder / "cam_0_000000000000_keypoints.json").write_text(json.dumps({"people": [person]}))
    out = tmp_path / "tracks.csv"
    status = main(["-q", "import-tracks", str(folder), "--out", str(out)])
    _one_line_error(capsys, status, "keypoints.json", "not finite")
    assert not out.exists()


def test_tracks_out_is_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tracks = tmp_path / "in.csv"
    tracks.write_text("video,frame,point,x,y\ncam_0,0,knee,10,10\n")
    status = main(["-q", "import-tracks", str(tracks), "--out", str(tmp_path)])
    _one_line_error(capsys, status, "is a folder")


DLC = """scorer,S,S,S
bodyparts,nose,nose,nose
coords,x,y,likelihood
{index},10.5,20.25,0.99
"""


@pytest.mark.parametrize(("index", "words"), [("-7", ["-7 is negative"]), ("1.0", ["'1.0' is not an integer"])])
def test_dlc_indexes_that_are_not_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], index: str, words: list[str]
) -> None:
    path = tmp_path / "cam_0DLC_resnet50.csv"
    path.write_text(DLC.format(index=index))
    status = main(["-q", "import-tracks", str(path), "--video", "cam_0", "--out", str(tmp_path / "t.csv")])
    _one_line_error(capsys, status, "line 4", *words)


def test_plain_csv_frame_with_an_underscore(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "in.csv"
    path.write_text("video,frame,point,x,y\ncam_0,1_000,knee,10,10\n")
    status = main(["-q", "import-tracks", str(path), "--out", str(tmp_path / "t.csv")])
    _one_line_error(capsys, status, "'1_000' is not an integer")


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (("matrix = [ [ 300.0,", "matrix = [ [ true,"), ['"matrix" must be numbers, not true/false']),
        (("fisheye = false", 'fisheye = "false"'), ["fisheye = 'false' must be true or false"]),
    ],
)
def test_calibration_toml_with_true_false_where_numbers_or_flags_belong(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], change: tuple[str, str], words: list[str]
) -> None:
    calibration = _calibration(tmp_path / "calib.toml", ["cam_0", "cam_1"])
    text = calibration.read_text()
    assert change[0] in text, text
    calibration.write_text(text.replace(change[0], change[1], 1))
    args = ["-q", "import-calibration", str(calibration), *_videos(tmp_path), "--out", str(tmp_path / "ws")]
    _one_line_error(capsys, main(args), "calib.toml", *words)


def test_import_keeps_the_users_own_columns_of_the_rows_it_keeps(tmp_path: Path) -> None:
    out = tmp_path / "tracks.csv"
    out.write_text("video,frame,point,x,y,source,note\ncam_1,0,knee,5,5,label,checked by hand\n")
    new = tmp_path / "new.csv"
    new.write_text("video,frame,point,x,y\ncam_0,0,knee,10,10\n")
    assert main(["-q", "import-tracks", str(new), "--out", str(out)]) == 0
    lines = out.read_text().splitlines()
    assert lines[0].endswith(",note") and any(line.endswith(",checked by hand") for line in lines[1:])


def test_run_refuses_unknown_export_units_before_any_stage(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = main(["-q", "run", *_videos(tmp_path), "--out", str(tmp_path / "ws"), "--units", "furlong"])
    _one_line_error(capsys, status, "--units 'furlong'")
    assert not (tmp_path / "ws" / "register").exists()


def test_one_video_name_for_several_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    first, second = tmp_path / "a.csv", tmp_path / "b.csv"
    for path in (first, second):
        path.write_text(DLC.format(index="0"))
    status = main(
        ["-q", "import-tracks", str(first), str(second), "--video", "cam_0", "--out", str(tmp_path / "t.csv")]
    )
    _one_line_error(capsys, status, "b.csv", "--video cam_0 names one video")


def test_run_names_the_users_tracks_file_when_its_videos_are_not_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tracks = tmp_path / "mine.csv"
    tracks.write_text("video,frame,point,x,y\nleft,0,knee,10,10\n")
    status = main(["-q", "run", *_videos(tmp_path), "--out", str(tmp_path / "ws"), "--tracks", str(tracks)])
    _one_line_error(capsys, status, "mine.csv", "left are not among the videos given", "cam_0")


def test_a_tracks_row_with_a_cell_beyond_the_header(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "in.csv"
    path.write_text("video,frame,point,x,y,score\ncam_0,0,knee,10,10,0.9,extra\n")
    status = main(["-q", "import-tracks", str(path), "--out", str(tmp_path / "t.csv")])
    _one_line_error(capsys, status, "line 2", "expected 6 fields, found 7")


def test_openpose_folder_mixing_two_models(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "cam_0_json"
    folder.mkdir()
    for frame, count in ((0, 25), (1, 18)):
        person = {"pose_keypoints_2d": [10.0, 10.0, 0.9] * count}
        (folder / f"cam_0_{frame:012d}_keypoints.json").write_text(json.dumps({"people": [person]}))
    status = main(["-q", "import-tracks", str(folder), "--out", str(tmp_path / "t.csv")])
    _one_line_error(capsys, status, "000000000001_keypoints.json", "18 keypoints where", "has 25")


@pytest.mark.parametrize("units", ["cm", "centimeters", "Inches"])
def test_board_units_spelled_as_people_do(tmp_path: Path, units: str) -> None:
    from tracking.charuco import read_charuco_board

    path = tmp_path / "charuco.toml"
    path.write_text(f'columns = 4\nrows = 5\nboard_width = 8.5\nboard_height = 11\nunits = "{units}"\n')
    square = read_charuco_board(path).square_size
    assert square == pytest.approx((0.0254 if units == "Inches" else 0.01) * min(11 / 5, 8.5 / 4))
