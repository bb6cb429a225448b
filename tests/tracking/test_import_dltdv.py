"""DLTdv's and Argus's xypts files: points we place, written in each tool's pixels and column layout, read back in
OpenCV's pixels; offsets; what the file cannot say (the rows' direction of DLTdv's _X/_Y, the image height).
Then the whole way a DLTdv user takes: DLT coefficients and xypts of desynchronized cameras, solved."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from dynrecon.cli import main
from tracking.pixels import DltPixels
from tracking.tracks import read_tracks

from ..dlt_files import coefficients, tool_points, write_dlt_columns, write_xypts
from ..sfm.test_calibration_dlt import HEIGHT, WIDTH, _project, _rig, _videos
from ..sfm.test_import_calibration import _write_video

NAMES = ["pt1", "pt2", "pt10"]


def _truth(frames: int = 6, cameras: int = 3) -> np.ndarray:
    """(F, P, C, 2) OpenCV pixels, a few NaN."""
    rng = np.random.default_rng(3)
    xy = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], (frames, len(NAMES), cameras, 2))
    xy[1, 0, 2] = np.nan
    xy[4, 2, 0] = np.nan
    return xy


def _imported(path: Path) -> dict[tuple[str, int, str], np.ndarray]:
    tracks = read_tracks(path)
    return {(tracks.video[i], int(tracks.frame[i]), tracks.point[i]): tracks.xy[i] for i in range(len(tracks))}


def _expected(xy: np.ndarray, names: list[str], offsets: tuple[int, ...] = (0, 0, 0)) -> dict:
    return {
        (names[c], f + offsets[c], NAMES[p]): xy[f, p, c]
        for f in range(xy.shape[0])
        for p in range(xy.shape[1])
        for c in range(xy.shape[2])
        if not np.isnan(xy[f, p, c, 0]) and f + offsets[c] >= 0
    }


def _assert_same(found: dict, expected: dict) -> None:
    assert found.keys() == expected.keys()
    for key, value in expected.items():
        np.testing.assert_allclose(found[key], value, atol=1e-5)


@pytest.mark.parametrize(
    ("style", "pixels", "args"),
    [
        ("dltdv7", DltPixels.DLTDV7, ["--pixels", "dltdv7"]),
        ("dltdv84", DltPixels.DLTDV8, []),  # 8.4's _U/_V columns say DLTdv 8
        ("argus", DltPixels.ARGUS, []),  # Argus's columns, sorted by name (pt10 before pt2)
    ],
)
def test_each_tools_points(tmp_path: Path, style: str, pixels: DltPixels, args: list[str]) -> None:
    xy = _truth()
    path = write_xypts(tmp_path / "trial_xypts.csv", tool_points(xy, pixels, HEIGHT), NAMES, style=style)
    videos = _videos(tmp_path)
    out = tmp_path / "tracks.csv"
    assert main(["import-tracks", str(path), "--videos", *map(str, videos), "--out", str(out), *args]) == 0
    _assert_same(_imported(out), _expected(xy, ["cam1", "cam2", "cam3"]))


def test_offsets_and_names_without_videos(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """DLTdv 8 (top-down rows) needs no video: cameras are cam1...; the sibling offsets file moves each camera's
    rows to its own frames (row n holds frame n + offset), and rows before a video's start are left out."""
    xy = _truth()
    path = write_xypts(tmp_path / "DLTdv8_data_xypts.csv", tool_points(xy, DltPixels.DLTDV8, HEIGHT), NAMES)
    offsets = np.zeros((xy.shape[0], 3))
    offsets[:, 1], offsets[:, 2] = 2, -1
    offsets[3, 2] = 0  # DLTdv writes 0 where nothing was digitized: the mean of the others is taken
    lines = ["cam1_offset,cam2_offset,cam3_offset"] + [",".join(f"{v:g}" for v in row) for row in offsets]
    (tmp_path / "DLTdv8_data_offsets.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    out = tmp_path / "tracks.csv"
    assert main(["import-tracks", str(path), "--pixels", "dltdv8", "--out", str(out)]) == 0
    _assert_same(_imported(out), _expected(xy, ["cam1", "cam2", "cam3"], (0, 2, -1)))
    assert "before their video's first frame" in caplog.text


@pytest.mark.parametrize(
    ("args", "what"),
    [
        ([], "--pixels dltdv7"),  # DLTdv's _X/_Y: 5-7 or 8.0-8.3
        (["--pixels", "dltdv7"], "--videos cam1.mp4"),  # bottom-up rows need the heights
        (["--pixels", "dltdv8", "--videos", "a.mp4"], "3 cameras, but 1 videos"),
    ],
)
def test_what_the_file_cannot_say(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], what: str
) -> None:
    path = write_xypts(tmp_path / "t_xypts.csv", _truth(), NAMES)
    assert main(["import-tracks", str(path), "--out", str(tmp_path / "tracks.csv"), *args]) == 2
    error = capsys.readouterr().err
    assert what in error and error.count("\n") == 1
    assert not (tmp_path / "tracks.csv").exists()


def test_dltdv_calibration_and_points_solved_without_synchronization(tmp_path: Path) -> None:
    """A DLTdv 7 user's files: easyWand's coefficients and DLTdv's xypts of three cameras started 0, 2 and 5 frames
    late. import-calibration + import-tracks + solve put the points where they were (within 1 mm of 4 m)."""
    Ks, Rs, ts = _rig()
    table = np.stack([coefficients(K, R, t, DltPixels.DLTDV7, HEIGHT) for K, R, t in zip(Ks, Rs, ts, strict=True)])
    calibration = write_dlt_columns(tmp_path / "wand_dltCoefs.csv", table)
    frames, fps, late = 90, 25.0, (0, 2, 5)
    time = np.arange(frames) / fps
    centres = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [-0.2, 0.3, -0.1], [0.1, 0.1, 0.35]])
    truth = centres[None] + 0.25 * np.stack(
        [
            np.sin(2.1 * time + k)[:, None] * [1, 0.5, 0.2] + np.cos(1.3 * time + 2 * k)[:, None] * [0.2, 1, 0.4]
            for k in range(4)
        ],
        axis=1,
    )  # (F, P, 3) in the calibration's metres
    names = [f"pt{p + 1}" for p in range(4)]
    # DLTdv's rows are camera 1's frames; each camera's own video starts `late` frames into the motion
    uv = np.full((frames, 4, 3, 2), np.nan)
    for c, (K, R, t) in enumerate(zip(Ks, Rs, ts, strict=True)):
        xy = _project(K, R, t, truth.reshape(-1, 3)).reshape(frames, 4, 2)
        uv[: frames - late[c], :, c] = tool_points(xy, DltPixels.DLTDV7, HEIGHT)[late[c] :]
    points = write_xypts(tmp_path / "trial_xypts.csv", uv, names)
    videos = [tmp_path / f"cam{c + 1}.mp4" for c in range(3)]
    for c, video in enumerate(videos):
        _write_video(video, frames - late[c], (WIDTH, HEIGHT), fps)
    ws = tmp_path / "ws"
    assert main(["import-calibration", str(calibration), *map(str, videos), "--out", str(ws)]) == 0
    args = ["import-tracks", str(points), "--pixels", "dltdv7", "--videos", *map(str, videos)]
    assert main([*args, "--out", str(ws / "tracks.csv")]) == 0
    assert (
        main(
            ["solve", "--cameras", str(ws / "cameras.json"), "--tracks", str(ws / "tracks.csv"), "--out", str(ws / "r")]
        )
        == 0
    )
    result = pd.read_csv(ws / "r" / "points3d.csv")
    result = result[result.observed == 1]
    shift = result.video.map({f"cam{c + 1}": late[c] for c in range(3)})
    true = truth[result.frame + shift, result.point.str[2:].astype(int) - 1]
    errors = np.linalg.norm(result[["x", "y", "z"]].to_numpy() - true, axis=1)
    assert np.median(errors) < 1e-3, np.median(errors)
