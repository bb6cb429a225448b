"""SLEAP's analysis HDF5, as written by sleap-io (tests/data/sleap), and SLEAP's older layouts."""

from __future__ import annotations

import csv
import logging
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from tracking.import_sleap import video_name_from_sleap
from tracking.importing import Format, ImportOptions, detect_format, run_import
from tracking.tracks import read_tracks

DATA = Path(__file__).resolve().parents[1] / "data" / "sleap"


def truth() -> dict[tuple[int, str, str], tuple[float, float, float]]:
    with (DATA / "truth.csv").open() as handle:
        return {
            (int(r["frame"]), r["track"], r["node"]): (float(r["x"]), float(r["y"]), float(r["score"]))
            for r in csv.DictReader(handle)
        }


def imported(path: Path, out: Path, **options) -> dict[tuple[int, str], tuple[float, float, float]]:
    tracks = read_tracks(run_import([path], out, ImportOptions(**options)))
    assert set(tracks.video) == {"cam1"}
    assert set(tracks.extra["source"]) == {"sleap"}
    return {
        (int(tracks.frame[i]), tracks.point[i]): (
            float(tracks.xy[i, 0]),
            float(tracks.xy[i, 1]),
            float(tracks.extra["score"][i]),
        )
        for i in range(len(tracks))
    }


def same(got: dict, want: dict) -> bool:
    """The same points with the same (x, y, score) to the 3 decimals tracks.csv keeps."""
    return got.keys() == want.keys() and all(np.allclose(got[k], want[k], atol=1e-3) for k in want)


def expected(names: dict[str, str]) -> dict[tuple[int, str], tuple[float, float, float]]:
    """truth under point names track -> prefix ('' = bare node names; a track not in `names` is left out)."""
    return {(f, f"{names[t]}_{n}" if names[t] else n): v for (f, t, n), v in truth().items() if t in names}


@pytest.mark.parametrize("name", ["cam1.analysis.h5", "cam1.standard.analysis.h5"])
def test_both_presets_import_every_point_with_its_score(tmp_path: Path, name: str, caplog) -> None:
    path = DATA / name
    assert detect_format(path) is Format.SLEAP
    with caplog.at_level(logging.WARNING):
        got = imported(path, tmp_path / "t.csv", video="cam1")
    assert same(got, expected({"mouseA": "mouseA", "mouseB": "mouseB"}))
    assert "2 tracks seen (mouseA, mouseB)" in caplog.text and "--person all" in caplog.text


def test_low_point_scores_are_not_called_guesses(tmp_path: Path, caplog) -> None:
    """SLEAP's point scores are confidence-map peaks of visible points, lower than DeepLabCut's likelihoods: no
    advice to leave them out (DeepLabCut's, tests/tracking/test_import_dlc.py)."""
    low = tmp_path / "cam1.analysis.h5"
    shutil.copy(DATA / "cam1.analysis.h5", low)
    with h5py.File(low, "r+") as f:
        f["point_scores"][...] = 0.3
    with caplog.at_level(logging.WARNING):
        got = imported(low, tmp_path / "t.csv")
    assert {round(v[2], 3) for v in got.values()} == {0.3}
    assert "confidence under" not in caplog.text and "--min-score" not in caplog.text


def test_sleaps_own_layouts_without_dims(tmp_path: Path) -> None:
    # SLEAP's export (before sleap-io's dims attribute): track, xy, node, frame
    legacy = tmp_path / "cam1.analysis.h5"
    shutil.copy(DATA / "cam1.analysis.h5", legacy)
    with h5py.File(legacy, "r+") as f:
        del f["tracks"].attrs["dims"]
    reference = imported(DATA / "cam1.analysis.h5", tmp_path / "a.csv")
    assert imported(legacy, tmp_path / "b.csv") == reference
    # transpose=False: frame, node, xy, track
    untransposed = tmp_path / "un" / "cam1.analysis.h5"
    untransposed.parent.mkdir()
    shutil.copy(DATA / "cam1.analysis.h5", untransposed)
    with h5py.File(untransposed, "r+") as f:
        tracks = f["tracks"][()]  # track, xy, node, frame
        scores = f["point_scores"][()]  # track, node, frame
        del f["tracks"], f["point_scores"]
        f["tracks"] = np.transpose(tracks, (3, 2, 1, 0))
        f["point_scores"] = np.transpose(scores, (2, 1, 0))
        f.attrs["transpose"] = False
    assert imported(untransposed, tmp_path / "c.csv") == reference


def test_person_numbers_tracks_by_how_much_they_are_seen(tmp_path: Path) -> None:
    path = DATA / "cam1.analysis.h5"  # mouseA: 35 points, mouseB: 27
    every = imported(path, tmp_path / "a.csv", every_person=True)
    assert same(every, expected({"mouseA": "person0", "mouseB": "person1"}))
    assert same(imported(path, tmp_path / "b.csv", person=1), expected({"mouseB": ""}))
    with pytest.raises(InputError, match=r"--person 2, but the file has 2 tracks \(mouseA, mouseB\)"):
        run_import([path], tmp_path / "c.csv", ImportOptions(person=2))


def test_the_cli_and_video_names(tmp_path: Path) -> None:
    out = tmp_path / "tracks.csv"
    assert main(["import-tracks", str(DATA / "cam1.analysis.h5"), "--person", "all", "--out", str(out)]) == 0
    assert {p.split("_")[0] for p in read_tracks(out).point} == {"person0", "person1"}
    assert set(read_tracks(out).video) == {"cam1"}  # from the file's video_path
    # SLEAP's export names, where a file has no video_path: <labels>.<index>_<video>.analysis.h5
    assert video_name_from_sleap(tmp_path / "cam2.predictions.000_cam2.analysis.h5") == "cam2"
    assert video_name_from_sleap(tmp_path / "labels.v001.predictions.analysis.h5") == "labels.v001"
    renamed = tmp_path / "predictions.000_front.analysis.h5"
    shutil.copy(DATA / "cam1.analysis.h5", renamed)
    with h5py.File(renamed, "r+") as f:
        del f["video_path"]
    assert video_name_from_sleap(renamed) == "front"
    with h5py.File(renamed, "r+") as f:
        f["video_path"] = "C:\\videos\\side.mp4"
    assert video_name_from_sleap(renamed) == "side"


def test_one_named_track_keeps_its_name_and_is_person_0(tmp_path: Path) -> None:
    one = tmp_path / "cam1.analysis.h5"
    shutil.copy(DATA / "cam1.analysis.h5", one)
    with h5py.File(one, "r+") as f:  # mouseA alone, as SLEAP exports a video where only one track was seen
        tracks, scores = f["tracks"][()][:1], f["point_scores"][()][:1]
        for name in ("tracks", "point_scores", "track_names"):
            del f[name]
        f["tracks"], f["point_scores"], f["track_names"] = tracks, scores, np.array([b"mouseA"])
        f["tracks"].attrs["dims"] = '["track", "xy", "node", "frame"]'
    assert same(imported(one, tmp_path / "a.csv"), expected({"mouseA": "mouseA"}))
    assert same(imported(one, tmp_path / "b.csv", person=0), expected({"mouseA": ""}))


def slp_truth() -> dict[tuple[str, int, str], tuple[float, float, str]]:
    with (DATA / "two_cameras_truth.csv").open() as handle:
        return {
            (r["video"], int(r["frame"]), f"{r['track']}_{r['node']}"): (float(r["x"]), float(r["y"]), r["score"])
            for r in csv.DictReader(handle)
        }


def test_a_slp_of_two_videos_with_a_corrected_instance(tmp_path: Path) -> None:
    """sleap-io's own .slp (tests/data/sleap/make_sleap_slp.py): both videos, the user's correction instead of the
    prediction it came from, a point not visible left out."""
    path = DATA / "two_cameras.slp"
    assert detect_format(path) is Format.SLEAP
    tracks = read_tracks(run_import([path], tmp_path / "t.csv", ImportOptions()))
    got = {
        (tracks.video[i], int(tracks.frame[i]), tracks.point[i]): (
            float(tracks.xy[i, 0]),
            float(tracks.xy[i, 1]),
            tracks.extra["score"][i],
        )
        for i in range(len(tracks))
    }
    want = slp_truth()
    assert got.keys() == want.keys()
    for key, (x, y, score) in want.items():
        assert got[key][:2] == pytest.approx((x, y), abs=1e-6)
        assert got[key][2] == ("" if not score else f"{float(score):.3f}")
    assert ("cam2", 4, "mouseB_tail") not in got
    every = read_tracks(run_import([path], tmp_path / "e.csv", ImportOptions(every_person=True)))
    assert {p.split("_")[0] for p in every.point} == {"person0", "person1"}  # numbered per video
    with pytest.raises(InputError, match=r"--video names one video, but the file holds 2 \(cam1, cam2\)"):
        run_import([path], tmp_path / "v.csv", ImportOptions(video="x"))


def slp_copy(tmp_path: Path, name: str, change) -> Path:
    path = tmp_path / name
    shutil.copy(DATA / "two_cameras.slp", path)
    with h5py.File(path, "r+") as f:
        change(f)
    return path


def untrack(f, tracks_too: bool) -> None:
    instances = f["instances"][()]
    instances["track"] = -1
    f["instances"][...] = instances
    if tracks_too:
        del f["tracks_json"]


def plain_instances(f) -> None:
    """A newer writer's layout (sleap-io.js's format 1.9 files): the instances as a plain integer array."""
    count = len(f["instances"])
    del f["instances"]
    f.create_dataset("instances", data=np.zeros((count, 8), dtype=np.int64))


def test_slp_files_this_reader_does_not_know_are_refused(tmp_path: Path) -> None:
    cases = [
        ("old.slp", lambda f: f["metadata"].attrs.__setitem__("format_id", 1.0), r"SLEAP file format 1 is not read"),
        ("new.slp", lambda f: f["metadata"].attrs.__setitem__("format_id", 3.0), r"SLEAP file format 3 is not read"),
        ("crops.slp", lambda f: f.create_dataset("video_crops", data=[[0, 0, 10, 10]]), r"its videos are crops"),
        (
            "untracked.slp",
            lambda f: untrack(f, tracks_too=True),
            r"two predicted instances with no track on frame 0 of cam1 \(track them in SLEAP",
        ),
        ("junk.slp", None, r"not a readable SLEAP .slp file"),
        ("plain.slp", plain_instances, r"its instances tables are plain arrays, not the named columns"),
    ]
    for name, change, message in cases:
        if change is None:
            path = tmp_path / name
            path.write_bytes(b"\x89HDF\r\n\x1a\n")
        else:
            path = slp_copy(tmp_path, name, change)
        with pytest.raises(InputError, match=message) as info:
            run_import([path], tmp_path / "o.csv", ImportOptions())
        assert "\n" not in str(info.value) and name in str(info.value)
        assert not (tmp_path / "o.csv").exists()


def test_two_predictions_on_one_track_are_refused_and_untracked_extras_left_out(tmp_path: Path, caplog) -> None:
    def second_prediction_on_track_0(f) -> None:  # frame 0 of cam1: mouseB's prediction moved to mouseA's track
        instances = f["instances"][()]
        instances["track"][1] = 0
        f["instances"][...] = instances

    twice = slp_copy(tmp_path, "twice.slp", second_prediction_on_track_0)
    with pytest.raises(InputError, match=r"two predicted instances with track 0 on frame 0 of cam1"):
        run_import([twice], tmp_path / "o.csv", ImportOptions())

    def one_untracked(f) -> None:
        instances = f["instances"][()]
        instances["track"][1] = -1
        f["instances"][...] = instances

    extra = slp_copy(tmp_path, "extra.slp", one_untracked)
    with caplog.at_level(logging.WARNING):
        tracks = read_tracks(run_import([extra], tmp_path / "e.csv", ImportOptions()))
    assert "1 untracked instances beside the tracked ones are left out" in caplog.text
    assert not any(p in ("head", "thorax", "tail") for p in tracks.point)  # no bare, scene-like points
    assert len(tracks) == len(slp_truth()) - 3  # mouseB's 3 points on cam1 frame 0


def test_broken_analysis_files_give_one_line_errors(tmp_path: Path) -> None:
    bad = tmp_path / "cam1.analysis.h5"
    shutil.copy(DATA / "cam1.analysis.h5", bad)
    with h5py.File(bad, "r+") as f:
        del f["node_names"]
        f["node_names"] = np.array([b"head", b"tail"])
    with pytest.raises(InputError, match=r"'tracks' has 3 nodes but 'node_names' 2") as info:
        run_import([bad], tmp_path / "o.csv", ImportOptions())
    assert "\n" not in str(info.value)
    assert not (tmp_path / "o.csv").exists()


def test_a_damaged_slp_gives_one_line(tmp_path: Path) -> None:
    """Three bytes written over one inside the file's structures (a mutation sweep, 2026-11-30): h5py raises
    RuntimeError there, which was a traceback."""
    data = (DATA / "two_cameras.slp").read_bytes()
    bad = tmp_path / "two_cameras.slp"
    bad.write_bytes(data[:18578] + b"abc" + data[18579:])
    with pytest.raises(InputError, match=r"not a readable SLEAP \.slp file \(.*bad symbol table") as info:
        run_import([bad], tmp_path / "o.csv", ImportOptions())
    assert "\n" not in str(info.value)
    assert not (tmp_path / "o.csv").exists()
