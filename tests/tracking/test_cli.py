from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from tracking.accuracy import labels_every
from tracking.synthetic import SyntheticVideo
from tracking.tracks import read_tracks


def _workspace(tmp_path: Path, video: SyntheticVideo, every: int = 10) -> Path:
    assert video.path is not None
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "labeling.json").write_text(json.dumps({"videos": {"cam0": str(video.path)}, "points": video.names}))
    lines = ["video,frame,point,x,y,source"]
    for name, marks in labels_every(video, every).items():
        for frame, xy in marks.items():
            row = ",,hidden" if xy is None else f"{xy[0]},{xy[1]},label"
            lines.append(f"cam0,{frame},{name},{row}")
    (ws / "labels.csv").write_text("\n".join(lines) + "\n")
    return ws


def test_track_command_writes_labels_and_accurate_tracks(
    tmp_path: Path, small_video: SyntheticVideo, capsys: pytest.CaptureFixture[str]
) -> None:
    ws = _workspace(tmp_path, small_video)
    assert main(["track", str(ws)]) == 0
    assert capsys.readouterr().out.strip() == str(ws / "tracks.csv")
    tracks = read_tracks(ws / "tracks.csv")
    assert set(tracks.video) == {"cam0"}
    errors = []
    for i in range(len(tracks)):
        p, f = small_video.names.index(tracks.point[i]), int(tracks.frame[i])
        source, score = tracks.extra["source"][i], float(tracks.extra["score"][i])
        assert small_video.visible[f, p] or source == "track"  # hidden labels never become rows
        if source == "label":
            assert f % 10 == 0 and score == 1.0
            np.testing.assert_allclose(tracks.xy[i], small_video.uv[f, p], atol=1e-9)
        else:
            assert source == "track" and 0.0 <= score <= 1.0 and f % 10 != 0
            errors.append(np.hypot(*(tracks.xy[i] - small_video.uv[f, p])))
    assert len(errors) > 0.8 * 36 * len(small_video.names)
    assert np.median(errors) < 1.0 and np.percentile(errors, 95) < 3.0


def test_track_only_given_videos_keeps_the_rest(tmp_path: Path, small_video: SyntheticVideo) -> None:
    ws = _workspace(tmp_path, small_video, every=20)
    with (ws / "labels.csv").open("a") as handle:
        handle.write("other,3,m0,5.0,6.0,label\n")
    (ws / "tracks.csv").write_text(
        "video,frame,point,x,y,source,score\nother,3,m0,1.0,1.0,track,0.5\nother,4,m0,2.0,2.0,track,0.5\n"
    )
    assert small_video.path is not None
    out = tmp_path / "custom.csv"
    (ws / "tracks.csv").replace(out)
    assert (
        main(
            [
                "track",
                str(ws),
                "--videos",
                str(small_video.path),
                "--out",
                str(out),
                "--method",
                "lk",
                "--blend",
                "best",
            ]
        )
        == 0
    )
    tracks = read_tracks(out)
    other = {
        (int(tracks.frame[i]), tracks.extra["source"][i]): tuple(tracks.xy[i])
        for i in range(len(tracks))
        if tracks.video[i] == "other"
    }
    assert other == {(3, "label"): (5.0, 6.0), (4, "track"): (2.0, 2.0)}  # the new label replaced the old row
    assert "cam0" in set(tracks.video)


def test_track_command_errors_are_one_line(
    tmp_path: Path, small_video: SyntheticVideo, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["track", str(tmp_path / "missing")]) == 2
    assert "workspace folder not found" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["track", str(empty)]) == 2
    err = capsys.readouterr().err
    assert "no videos found" in err and "no labels.csv" in err and "label the subject first" in err
    (empty / "labels.csv").write_text("video,frame,point,x,y\n")  # labels, but the videos elsewhere
    assert main(["track", str(empty)]) == 2
    assert "pass --videos V1 V2" in capsys.readouterr().err
    ws = _workspace(tmp_path, small_video)
    (ws / "labels.csv").write_text("video,frame,point,x,y,source\ncam0,zero,m0,1,2,label\n")
    assert main(["track", str(ws)]) == 2
    err = capsys.readouterr().err
    assert "labels.csv:line 2: frame 'zero' is not an integer" in err and err.count("\n") == 1
    (ws / "labeling.json").write_text('{"videos": {"cam0": "nowhere.mp4"}}')
    assert main(["track", str(ws)]) == 2
    assert "nowhere.mp4 not found" in capsys.readouterr().err
    assert main(["track", str(ws), "--min-score", "2"]) == 2
    assert capsys.readouterr().err == "dynrecon track: error: --min-score 2.0 is outside 0..1\n"
    (tmp_path / "notes.txt").write_text("my notes\n")  # an --out that exists and is no tracks file
    (tmp_path / "second").mkdir()
    ws = _workspace(tmp_path / "second", small_video)
    assert main(["track", str(ws), "--out", str(tmp_path / "notes.txt")]) == 2
    err = capsys.readouterr().err
    assert "notes.txt" in err and "the existing tracks file this run adds its videos to" in err
    assert (tmp_path / "notes.txt").read_text() == "my notes\n"
    assert main(["import-tracks", str(tmp_path / "x.csv"), "--out", str(tmp_path / "y.csv"), "--min-score", "nan"]) == 2
    assert capsys.readouterr().err == "dynrecon import-tracks: error: --min-score nan is outside 0..1\n"


def test_track_without_labels_is_refused_and_keeps_the_tracks(
    tmp_path: Path, small_video: SyntheticVideo, capsys: pytest.CaptureFixture[str]
) -> None:
    assert small_video.path is not None
    ws = tmp_path / "ws"
    (ws / "videos").mkdir(parents=True)
    (ws / "videos" / "cam9.avi").symlink_to(small_video.path)
    assert main(["track", str(ws)]) == 2
    err = capsys.readouterr().err
    assert "labels.csv: not found: no labels for cam9" in err and "dynrecon label" in err and err.count("\n") == 1
    assert not (ws / "tracks.csv").exists()
    kept = "video,frame,point,x,y,source\ncam9,0,m0,1,2,imported\n"  # e.g. imported detections
    (ws / "tracks.csv").write_text(kept)
    for labels in ("", "video,frame,point,x,y,source\n", "video,frame,point,x,y,source\ncamQ,0,m0,1,2,label\n"):
        (ws / "labels.csv").write_text(labels)
        assert main(["track", str(ws)]) == 2
        err = capsys.readouterr().err
        assert "labels.csv: has no labels for cam9" in err and "tracks.csv left as it was" in err
        assert ("(it labels camQ)" in err) == ("camQ" in labels)
        assert (ws / "tracks.csv").read_text() == kept


def test_import_tracks_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "in.csv"
    src.write_text("video,frame,point,x,y,score\nv,0,Nose,1,2,0.9\nv,1,Nose,1,2,0.1\nv,0,Neck,3,4,0.9\n")
    out = tmp_path / "ws" / "tracks.csv"
    assert (
        main(
            [
                "import-tracks",
                str(src),
                "--out",
                str(out),
                "--map",
                "Nose=nose",
                "--drop-unmapped",
                "--min-score",
                "0.5",
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.strip() == str(out)
    tracks = read_tracks(out)
    assert list(tracks.point) == ["nose"] and tracks.extra["source"] == ["csv"]
    assert main(["import-tracks", str(src), "--out", str(out), "--map", "broken"]) == 2
    assert "--map: 'broken' is not old=new" in capsys.readouterr().err
    assert main(["import-tracks", str(tmp_path / "nope.csv"), "--out", str(out)]) == 2
    assert "nope.csv: file not found" in capsys.readouterr().err


def test_a_point_the_tracker_loses_is_named_with_its_frames(
    tmp_path: Path, small_video: SyntheticVideo, caplog: pytest.LogCaptureFixture
) -> None:
    """A label on a spot without texture (Pose2Sim's swim cap): the tracker finds it on no other frame. The log gave
    only the video's totals; now a warning names the point, its frames found and the stretch without it."""
    import logging

    ws = _workspace(tmp_path, small_video)
    assert small_video.frames is not None
    first = small_video.frames[0]
    gray = first if first.ndim == 2 else first.mean(axis=2)
    # the flattest 9x9 patch of the first frame, away from the border
    variance = np.array(
        [[gray[y - 4 : y + 5, x - 4 : x + 5].var() for x in range(20, 300, 4)] for y in range(20, 220, 4)]
    )
    y, x = np.unravel_index(int(np.argmin(variance)), variance.shape)
    with (ws / "labels.csv").open("a") as handle:
        handle.write(f"cam0,0,ghost,{20 + 4 * x},{20 + 4 * y},label\n")
    with caplog.at_level(logging.WARNING):
        assert main(["track", str(ws)]) == 0
    said = [r.getMessage() for r in caplog.records if "lost by the tracker" in r.getMessage()]
    found = re.search(r"'ghost' on (\d+) of 40 frames \(none in (\d+)-39\)", said[0]) if len(said) == 1 else None
    assert found is not None and int(found[1]) < 20, said
    assert not any(f"'{name}'" in said[0] for name in small_video.names)  # the tracked markers are not named
