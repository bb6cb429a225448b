from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynrecon.errors import InputError
from tracking.import_openpose import BODY_25
from tracking.importing import Format, ImportOptions, detect_format, parse_mapping, run_import
from tracking.tracks import Tracks, read_tracks, write_tracks

SCORER = "DLC_resnet50_demoJan1shuffle1_1000"
DLC = f"""scorer,{SCORER},{SCORER},{SCORER},{SCORER},{SCORER},{SCORER}
bodyparts,nose,nose,nose,tail,tail,tail
coords,x,y,likelihood,x,y,likelihood
0,10.5,20.25,0.99,30.0,40.0,0.2
1,11.5,21.25,0.98,,,
2,12.5,22.25,0.97,32.0,42.0,0.95
"""

DLC_MULTI = """scorer,S,S,S,S,S,S
individuals,mouse1,mouse1,mouse1,mouse2,mouse2,mouse2
bodyparts,snout,snout,snout,snout,snout,snout
coords,x,y,likelihood,x,y,likelihood
0,1.0,2.0,0.9,5.0,6.0,0.8
"""

DLC_LABELED = """scorer,me,me
bodyparts,nose,nose
coords,x,y
labeled-data/cam2/img007.png,3.5,4.5
labeled-data/cam2/img012.png,5.5,6.5
"""


def _rows(tracks: Tracks) -> dict[tuple[str, int, str], tuple[float, float, str, str]]:
    return {
        (tracks.video[i], int(tracks.frame[i]), tracks.point[i]): (
            float(tracks.xy[i, 0]),
            float(tracks.xy[i, 1]),
            tracks.extra["source"][i],
            tracks.extra["score"][i],
        )
        for i in range(len(tracks))
    }


def test_deeplabcut_csv_with_threshold_and_mapping(tmp_path: Path) -> None:
    src = tmp_path / "cam01DLC_resnet50_demoJan1shuffle1_1000.csv"
    src.write_text(DLC)
    assert detect_format(src) is Format.DLC
    out = run_import([src], tmp_path / "tracks.csv", ImportOptions(mapping={"nose": "head"}, min_score=0.5))
    rows = _rows(read_tracks(out))
    assert rows == {
        ("cam01", 0, "head"): (10.5, 20.25, "dlc", "0.990"),
        ("cam01", 1, "head"): (11.5, 21.25, "dlc", "0.980"),
        ("cam01", 2, "head"): (12.5, 22.25, "dlc", "0.970"),
        ("cam01", 2, "tail"): (32.0, 42.0, "dlc", "0.950"),  # frame 0's tail is below 0.5, frame 1's is empty
    }


def test_deeplabcut_multi_animal_and_labeled_data(tmp_path: Path) -> None:
    multi = tmp_path / "multi.csv"
    multi.write_text(DLC_MULTI)
    labeled = tmp_path / "CollectedData_me.csv"
    labeled.write_text(DLC_LABELED)
    out = run_import([multi], tmp_path / "a.csv", ImportOptions(video="v"))
    assert set(_rows(read_tracks(out))) == {("v", 0, "mouse1_snout"), ("v", 0, "mouse2_snout")}
    out = run_import([labeled], tmp_path / "b.csv", ImportOptions(format=Format.DLC, video="cam2"))
    rows = _rows(read_tracks(out))
    assert rows[("cam2", 7, "nose")] == (3.5, 4.5, "dlc", "")
    assert rows[("cam2", 12, "nose")] == (5.5, 6.5, "dlc", "")


def test_openpose_folder_body25(tmp_path: Path) -> None:
    folder = tmp_path / "cam03_json"
    folder.mkdir()
    for frame in (0, 1, 5):
        flat = []
        for k in range(25):
            flat += [100.0 + k + frame, 200.0 + k, 0.0 if k == 3 else 0.1 + 0.03 * k]
        people = [{"pose_keypoints_2d": flat}] if frame != 1 else []
        (folder / f"cam03_{frame:012d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))
    assert detect_format(folder) is Format.OPENPOSE
    out = run_import(
        [folder],
        tmp_path / "tracks.csv",
        ImportOptions(min_score=0.2, mapping={"Nose": "nose", "RWrist": "wrist_r"}, drop_unmapped=True),
    )
    rows = _rows(read_tracks(out))
    # Nose has confidence 0.1 (< 0.2): dropped; RWrist (k=4) 0.22 kept; frame 1 has nobody.
    assert set(rows) == {("cam03", 0, "wrist_r"), ("cam03", 5, "wrist_r")}
    assert rows[("cam03", 5, "wrist_r")][:3] == (109.0, 204.0, "openpose")
    out = run_import([folder], tmp_path / "all.csv", ImportOptions())
    points = set(read_tracks(out).point)
    assert points == set(BODY_25) - {"RElbow"}  # k=3 has confidence 0: missing


def test_plain_csv_with_score_column_and_merge_keeps_labels_and_other_videos(tmp_path: Path) -> None:
    out = tmp_path / "tracks.csv"
    write_tracks(
        out,
        Tracks.from_rows(
            [("a", 0, "p", 1.0, 2.0), ("a", 1, "p", 3.0, 4.0), ("b", 0, "p", 5.0, 6.0)],
            source=["label", "track", "track"],
            score=["1.000", "0.5", "0.7"],
        ),
    )
    src = tmp_path / "plain.csv"
    src.write_text("video,frame,point,x,y,likelihood\na,0,p,9,9,0.9\na,2,p,7,8,0.9\na,3,p,7,8,0.1\n")
    run_import([src], out, ImportOptions(min_score=0.5))
    rows = _rows(read_tracks(out))
    assert rows == {
        ("a", 0, "p"): (1.0, 2.0, "label", "1.000"),  # the manual label wins over the import
        ("a", 2, "p"): (7.0, 8.0, "csv", "0.900"),  # the old tracked row of video a is replaced
        ("b", 0, "p"): (5.0, 6.0, "track", "0.7"),  # other videos are untouched
    }
    # the replaced row (a, 1) is in a copy kept beside the file, with a warning; the same import again replaces
    # nothing new and keeps no other copy
    kept = sorted(tmp_path.glob("tracks.before-*.csv"))
    assert len(kept) == 1 and ("a", 1, "p") in _rows(read_tracks(kept[0]))
    run_import([src], out, ImportOptions(min_score=0.5))
    assert len(sorted(tmp_path.glob("tracks.before-*.csv"))) == 1


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("bad.csv", "scorer,a,a\nbodyparts,n,n\ncoords,x,y\n0,1.0,oops\n", r"bad.csv:line 4: 'oops' in column 3"),
        ("nohead.csv", "scorer,a,a\ncoords,x,y\n0,1,2\n", r"nohead.csv:line 3: no 'bodyparts' header row"),
        ("semi.csv", "scorer;a;a\nbodyparts;n;n\ncoords;x;y\n0;1;2\n", r"semi.csv:line 1: .*separated by ';'"),
        ("noy.csv", "scorer,a\nbodyparts,n\ncoords,x\n0,1\n", r"noy.csv:coords row: point 'n' lacks an x or y"),
        ("short.csv", "scorer,a,a\nbodyparts,n,n\ncoords,x,y\n0,1\n", r"short.csv:line 4: expected at least 3 fields"),
        ("frame.csv", "scorer,a,a\nbodyparts,n,n\ncoords,x,y\nabc,1,2\n", r"frame.csv:line 4: cannot tell the frame"),
        ("plain.csv", "video,frame,point,x\na,0,p,1\n", r"plain.csv:line 1: header lacks column\(s\) y"),
        ("plain2.csv", "video,frame,point,x,y,score\na,0,p,1,2,high\n", r"plain2.csv:line 2: score 'high'"),
        ("plain3.csv", "video,frame,point,x,y,score\na,0,p,1,2,inf\n", r"plain3.csv:line 2: .*confidence inf"),
        ("plain4.csv", "video,frame,point,x,y,score\na,0,p,1,2,-1\n", r"plain4.csv:line 2: .*confidence -1"),
        ("plain5.csv", "video,frame,point,x,y\na,0,p,1e300,2\n", r"plain5.csv:line 2: .*not a position"),
        ("plain6.csv", "video,frame,point,x,y\n../x,0,p,1,2\n", r"plain6.csv: video name '\.\./x' contains a path"),
    ],
)
def test_malformed_files_give_one_line_errors(tmp_path: Path, name: str, text: str, message: str) -> None:
    src = tmp_path / name
    src.write_text(text)
    fmt = Format.CSV if name.startswith("plain") else Format.DLC
    with pytest.raises(InputError, match=message) as info:
        run_import([src], tmp_path / "out.csv", ImportOptions(format=fmt))
    assert "\n" not in str(info.value)
    assert not (tmp_path / "out.csv").exists()


def test_stray_json_files_of_another_name_are_left_out(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Pose2Sim's demo folder cam03_json holds cam03.0000.json ... and two del_000000_0.json-like leftovers, whose
    frame numbers repeat the main files': the main pattern is read, the strays named in a warning."""
    folder = tmp_path / "cam03_json"
    folder.mkdir()
    flat = [v for k in range(25) for v in (100.0 + k, 200.0 + k, 0.9)]
    for frame in range(4):
        (folder / f"cam03.{frame:04d}.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": flat}]}))
    for name in ("del_000000_0.json", "del_000001_0.json"):
        (folder / name).write_text(json.dumps({"people": [{"pose_keypoints_2d": [0.0] * 75}]}))

    out = run_import([folder], tmp_path / "tracks.csv", ImportOptions())

    assert sorted(set(read_tracks(out).frame)) == [0, 1, 2, 3]
    assert any(
        "2 of its 6 JSON files are named unlike the others" in m and "del_000000_0.json" in m for m in caplog.messages
    )


def test_malformed_openpose(tmp_path: Path) -> None:
    bad = tmp_path / "x_000000000004_keypoints.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match=r"x_000000000004_keypoints\.json: not valid JSON"):
        run_import([bad], tmp_path / "o.csv", ImportOptions())
    bad.write_text(json.dumps({"people": [{"pose_keypoints_2d": [1, 2]}]}))
    with pytest.raises(InputError, match="not a list of x, y, c triplets"):
        run_import([bad], tmp_path / "o.csv", ImportOptions())
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match=r"no \.json files"):
        run_import([empty], tmp_path / "o.csv", ImportOptions())


def test_mapping_parser_and_collisions(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert parse_mapping("a=b, c = d ,") == {"a": "b", "c": "d"}
    for bad in ("a", "=b", "a=", "a=b,a=c"):
        with pytest.raises(InputError, match="--map"):
            parse_mapping(bad)
    src = tmp_path / "two.csv"
    src.write_text("video,frame,point,x,y\nv,0,a,1,1\nv,0,b,2,2\n")
    with pytest.raises(InputError, match="two detections of point 'z'"):
        run_import([src], tmp_path / "o.csv", ImportOptions(mapping={"a": "z", "b": "z"}))
    # a name no detection gives (a typo, or a point never detected): said, naming the names detected
    import logging

    with caplog.at_level(logging.WARNING):
        run_import([src], tmp_path / "o.csv", ImportOptions(mapping={"foo": "bar", "a": "z"}))
    said = [r.getMessage() for r in caplog.records if "--map renames" in r.getMessage()]
    assert len(said) == 1 and "'foo', which no imported detection names" in said[0] and said[0].endswith("a, b")


def test_an_empty_deeplabcut_file_is_said_empty(tmp_path: Path) -> None:
    from tracking.importing import Format

    empty = tmp_path / "camDLC_resnet50.csv"
    empty.write_text("")
    with pytest.raises(InputError, match="the file is empty"):
        run_import([empty], tmp_path / "o.csv", ImportOptions(format=Format.DLC, video="cam"))


def test_imported_rows_are_float_exact(tmp_path: Path) -> None:
    src = tmp_path / "p.csv"
    src.write_text("video,frame,point,x,y\nv,3,a,0.1,1e-3\n")
    tracks = read_tracks(run_import([src], tmp_path / "o.csv", ImportOptions()))
    np.testing.assert_array_equal(tracks.xy, [[0.1, 1e-3]])


def test_body_25b_keypoints_are_told_from_body_25(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Pose2Sim's default OpenPose model, BODY_25B, writes 25 triplets as BODY_25 does, in another order (eyes and
    ears at 1-4, the neck at 17): a standing person written in either order is imported with the right names
    (the nose above the neck), and poses that cannot tell them apart are named as BODY_25 with a warning."""
    from tracking.import_openpose import BODY_25B

    where = {  # a standing person, facing the camera (image y down)
        "Nose": (100, 40), "LEye": (105, 35), "REye": (95, 35), "LEar": (110, 38), "REar": (90, 38),
        "Neck": (100, 60), "Head": (100, 25), "LShoulder": (120, 62), "RShoulder": (80, 62),
        "LElbow": (125, 90), "RElbow": (75, 90), "LWrist": (128, 115), "RWrist": (72, 115), "MidHip": (100, 120),
        "LHip": (110, 120), "RHip": (90, 120), "LKnee": (110, 160), "RKnee": (90, 160), "LAnkle": (110, 200),
        "RAnkle": (90, 200), "LBigToe": (115, 208), "LSmallToe": (118, 206), "LHeel": (108, 204),
        "RBigToe": (85, 208), "RSmallToe": (82, 206), "RHeel": (92, 204),
    }  # fmt: skip
    for model in (BODY_25, BODY_25B):
        folder = tmp_path / ("b" if model is BODY_25B else "a") / "cam01_json"
        folder.mkdir(parents=True)
        for frame in range(3):
            flat = [v for name in model for v in (where[name][0] + frame, where[name][1], 0.9)]
            (folder / f"cam01_{frame:012d}_keypoints.json").write_text(
                json.dumps({"people": [{"pose_keypoints_2d": flat}]})
            )
        tracks = read_tracks(run_import([folder], folder.parent / "tracks.csv", ImportOptions()))
        seen = {p: tracks.xy[i] for i, p in enumerate(tracks.point) if tracks.frame[i] == 0}
        assert set(seen) == set(model) and seen["Nose"][1] < seen["Neck"][1] and seen["LEye"][0] == 105
    caplog.clear()
    folder = tmp_path / "c" / "cam02_json"
    folder.mkdir(parents=True)
    # every keypoint as far from the nose: no head to tell the models by
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    flat = [100.0, 100.0, 0.9] + [v for a in angles for v in (100 + 50 * np.cos(a), 100 + 50 * np.sin(a), 0.9)]
    (folder / "cam02_000000000000_keypoints.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": flat}]}))
    assert "Neck" in read_tracks(run_import([folder], folder.parent / "tracks.csv", ImportOptions())).point
    assert "cannot be told apart" in caplog.text
    # that camera beside a BODY_25B one in one file: refused, not one name for two joints
    with pytest.raises(InputError, match="OpenPose keypoints named by two models: BODY_25 in cam02, BODY_25B in cam01"):
        run_import([folder, tmp_path / "b" / "cam01_json"], tmp_path / "both.csv", ImportOptions(video=None))


def test_deeplabcut_file_names_give_the_video_name() -> None:
    """The video a DeepLabCut file belongs to: its analysed-video names (DLC 2.x's `DLC_`, 2.0's `DeepCut_`), and a
    project's labelled frames, `labeled-data/<video>/CollectedData_<scorer>.csv`."""
    from tracking.import_dlc import video_name_from_dlc

    assert video_name_from_dlc(Path("cam01DLC_resnet50_projectJan1shuffle1_500000.csv")) == "cam01"
    assert video_name_from_dlc(Path("briefDeepCut_resnet50_TESTAug16shuffle1_5.csv")) == "brief"
    assert video_name_from_dlc(Path("proj/labeled-data/reachingvideo1/CollectedData_Mackenzie.h5")) == "reachingvideo1"
    assert video_name_from_dlc(Path("elsewhere/CollectedData_Mackenzie.csv")) == "CollectedData_Mackenzie"
    assert video_name_from_dlc(Path("cam02.csv")) == "cam02"


def test_an_import_never_writes_over_its_input(tmp_path: Path) -> None:
    """`import-tracks t.csv --out t.csv` rewrote the user's file in the importer's form (source, score columns):
    refused, the file untouched."""
    given = tmp_path / "t.csv"
    given.write_text("video,frame,point,x,y,source\na,0,p,1.0,2.0,marker\n", encoding="utf-8")
    before = given.read_bytes()
    with pytest.raises(InputError, match="is also the output"):
        run_import([given], given, ImportOptions())
    assert given.read_bytes() == before
