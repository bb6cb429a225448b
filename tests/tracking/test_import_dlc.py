"""DeepLabCut's .h5 output (written here the way DLC writes it: pandas `to_hdf(..., format="table")`) and its
multi-animal individuals (`--person`)."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from tracking.importing import Format, ImportOptions, detect_format, run_import
from tracking.tracks import read_tracks

SCORER = "DLC_resnet50_miceJan1shuffle1_50000"


def dlc_frame(individuals: list[str] | None, parts: list[str], values: np.ndarray) -> pd.DataFrame:
    """A DLC table: columns (scorer, [individuals,] bodyparts, coords), one row per frame; values (R, C)."""
    if individuals is None:
        tuples = [(SCORER, p, c) for p in parts for c in ("x", "y", "likelihood")]
        names = ["scorer", "bodyparts", "coords"]
    else:
        tuples = [(SCORER, i, p, c) for i in individuals for p in parts for c in ("x", "y", "likelihood")]
        names = ["scorer", "individuals", "bodyparts", "coords"]
    return pd.DataFrame(values, columns=pd.MultiIndex.from_tuples(tuples, names=names))


def write_h5(frame: pd.DataFrame, path: Path, key: str = "df_with_missing") -> Path:
    frame.to_hdf(path, key=key, format="table", mode="w")  # as DeepLabCut's analyze_videos does
    return path


def rows(path: Path) -> dict[tuple[str, int, str], tuple[float, float, str]]:
    tracks = read_tracks(path)
    return {
        (tracks.video[i], int(tracks.frame[i]), tracks.point[i]): (
            float(tracks.xy[i, 0]),
            float(tracks.xy[i, 1]),
            tracks.extra["score"][i],
        )
        for i in range(len(tracks))
    }


def two_mice() -> pd.DataFrame:
    """mouse1 seen on 2 frames, mouse2 on all 4; the `single` individual (a unique bodypart: the ball) on 3."""
    rng = np.random.default_rng(0)
    values = rng.uniform(10, 600, size=(4, 3 * 3)).round(2)
    values[:, 2::3] = 0.9
    values[2:, 0:3] = np.nan  # mouse1 lost on frames 2 and 3
    values[3, 6:9] = np.nan  # the ball lost on frame 3
    individuals = ["mouse1", "mouse2", "single"]
    tuples = [(SCORER, i, "snout", c) for i in individuals[:2] for c in ("x", "y", "likelihood")]
    tuples += [(SCORER, "single", "ball", c) for c in ("x", "y", "likelihood")]
    names = ["scorer", "individuals", "bodyparts", "coords"]
    return pd.DataFrame(values, columns=pd.MultiIndex.from_tuples(tuples, names=names))


def test_an_h5_imports_exactly_as_its_csv_export(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    values = rng.uniform(0, 1920, size=(30, 6)).round(3)
    values[:, 2::3] = rng.uniform(0, 1, size=(30, 2)).round(3)
    values[5, 0:3] = np.nan  # nose lost on frame 5
    frame = dlc_frame(None, ["nose", "tail"], values)
    h5 = write_h5(frame, tmp_path / f"cam01{SCORER}.h5")
    csv = tmp_path / f"cam02{SCORER}.csv"
    frame.to_csv(csv)  # DLC's own CSV is this export
    assert detect_format(h5) is Format.DLC
    from_h5 = rows(run_import([h5], tmp_path / "a.csv", ImportOptions(min_score=0.2)))
    from_csv = rows(run_import([csv], tmp_path / "b.csv", ImportOptions(min_score=0.2)))
    assert {(f, p): v for (_, f, p), v in from_h5.items()} == {(f, p): v for (_, f, p), v in from_csv.items()}
    assert {v for v, _, _ in from_h5} == {"cam01"}  # the video name from DLC's file name
    kept = (values[:, [2, 5]] >= 0.2) & np.isfinite(values[:, [0, 3]])
    assert len(from_h5) == int(kept.sum())
    assert from_h5["cam01", 7, "tail"][:2] == (values[7, 3], values[7, 4])


def test_labeled_data_and_tracklet_keys(tmp_path: Path) -> None:
    frame = dlc_frame(None, ["nose"], np.array([[3.5, 4.5, np.nan], [5.5, 6.5, np.nan]]))
    frame = frame.drop(columns="likelihood", level="coords")
    frame.index = ["labeled-data/cam2/img007.png", "labeled-data/cam2/img012.png"]
    got = rows(run_import([write_h5(frame, tmp_path / "CollectedData_me.h5")], tmp_path / "a.csv", ImportOptions()))
    assert got == {("CollectedData_me", 7, "nose"): (3.5, 4.5, ""), ("CollectedData_me", 12, "nose"): (5.5, 6.5, "")}
    # stitched multi-animal tracklets are stored under "tracks"
    h5 = write_h5(two_mice(), tmp_path / "cam1_el.h5", key="tracks")
    assert len(rows(run_import([h5], tmp_path / "b.csv", ImportOptions(video="cam1")))) == 2 + 4 + 3


def test_individuals_keep_dlc_names_by_default_with_a_warning(tmp_path: Path, caplog) -> None:
    h5 = write_h5(two_mice(), tmp_path / "cam1.h5")
    with caplog.at_level(logging.WARNING):
        got = rows(run_import([h5], tmp_path / "a.csv", ImportOptions(video="cam1")))
    assert {p for _, _, p in got} == {"mouse1_snout", "mouse2_snout", "ball"}
    assert "2 individuals seen (mouse1, mouse2)" in caplog.text and "--person all" in caplog.text


def test_person_numbers_individuals_by_how_much_they_are_seen(tmp_path: Path) -> None:
    h5 = write_h5(two_mice(), tmp_path / "cam1.h5")
    every = rows(run_import([h5], tmp_path / "a.csv", ImportOptions(video="cam1", every_person=True)))
    # mouse2 (4 frames) is person 0, mouse1 (2 frames) person 1; the unique bodypart keeps its name
    assert {p for _, _, p in every} == {"person0_snout", "person1_snout", "ball"}
    assert sum(p == "person0_snout" for _, _, p in every) == 4
    one = rows(run_import([h5], tmp_path / "b.csv", ImportOptions(video="cam1", person=1)))
    assert {p for _, _, p in one} == {"snout", "ball"}
    assert sum(p == "snout" for _, _, p in one) == 2  # mouse1's frames
    with pytest.raises(InputError, match=r"--person 2, but the file has 2 individuals \(mouse1, mouse2\)"):
        run_import([h5], tmp_path / "c.csv", ImportOptions(video="cam1", person=2))
    # a single-animal file is one subject, as OpenPose's single person: person 0
    single = write_h5(dlc_frame(None, ["nose"], np.ones((2, 3))), tmp_path / "one.h5")
    assert {p for _, _, p in rows(run_import([single], tmp_path / "d.csv", ImportOptions(person=0)))} == {"nose"}
    every_one = rows(run_import([single], tmp_path / "e.csv", ImportOptions(every_person=True)))
    assert {p for _, _, p in every_one} == {"person0_nose"}
    with pytest.raises(InputError, match="--person 1, but the file names no individuals"):
        run_import([single], tmp_path / "f.csv", ImportOptions(person=1))


def test_names_that_would_collide_are_refused(tmp_path: Path) -> None:
    # --person 0 names the most seen mouse's snout `snout`, as the scene's own `snout` (a unique bodypart) is named
    tuples = [(SCORER, i, "snout", c) for i in ("mouse1", "mouse2", "single") for c in ("x", "y", "likelihood")]
    names = ["scorer", "individuals", "bodyparts", "coords"]
    frame = pd.DataFrame(np.ones((2, 9)), columns=pd.MultiIndex.from_tuples(tuples, names=names))
    with pytest.raises(InputError, match=r"mouse1_snout and snout would both be imported as 'snout'"):
        run_import([write_h5(frame, tmp_path / "cam1.h5")], tmp_path / "a.csv", ImportOptions(person=0))


def test_a_series_is_not_a_dlc_table(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    pd.Series([1.0, 2.0]).to_hdf(path, key="df_with_missing", format="table")
    with pytest.raises(InputError, match="'df_with_missing' holds a Series, not DeepLabCut's table"):
        run_import([path], tmp_path / "a.csv", ImportOptions())


def test_the_cli_reads_h5_with_person_all(tmp_path: Path) -> None:
    h5 = write_h5(two_mice(), tmp_path / f"cam3{SCORER}_el.h5")
    out = tmp_path / "tracks.csv"
    assert main(["import-tracks", str(h5), "--person", "all", "--out", str(out)]) == 0
    assert {(v, p) for v, _, p in rows(out)} == {("cam3", "person0_snout"), ("cam3", "person1_snout"), ("cam3", "ball")}


def _plain_hdf5(path: Path) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=[1.0])


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_bytes(b"not hdf5 at all"), r"not a readable HDF5 file: damaged or truncated"),
        (  # a SLEAP analysis file cut short: no longer named a bad DeepLabCut file
            lambda p: p.write_bytes((Path(__file__).parents[1] / "data/sleap/cam1.analysis.h5").read_bytes()[:3000]),
            r"damaged or truncated \(export it again \(DeepLabCut's \.h5 or CSV, or SLEAP's analysis HDF5\)\)",
        ),
        (  # an HDF5 file that is not pandas': named as such
            lambda p: _plain_hdf5(p),
            r"not a readable pandas HDF5 file|no DeepLabCut table",
        ),
        (
            lambda p: pd.DataFrame({"a": [1.0]}).to_hdf(p, key="other", format="table"),
            r"table 'other' has column levels \[''\], not DeepLabCut's",
        ),
        (
            lambda p: (
                pd.DataFrame({"a": [1.0]}).to_hdf(p, key="one", format="table"),
                pd.DataFrame({"a": [1.0]}).to_hdf(p, key="two", format="table"),
            ),
            r"no DeepLabCut table in it \(keys: one, two\)",
        ),
    ],
)
def test_foreign_h5_files_give_one_line_errors(tmp_path: Path, make, message: str) -> None:
    path = tmp_path / "bad.h5"
    make(path)
    with pytest.raises(InputError, match=message) as info:
        run_import([path], tmp_path / "out.csv", ImportOptions())
    assert "\n" not in str(info.value) and "bad.h5" in str(info.value)
    assert not (tmp_path / "out.csv").exists()


def test_a_damaged_attribute_is_refused_before_pytables_reads_it(tmp_path: Path) -> None:
    """A SLEAP analysis file with one chunk of bytes repeated (found by a mutation sweep, 2026-11-30): h5py raised
    RuntimeError (a traceback), and PyTables, reading it as DeepLabCut's, crashed the process (a segmentation fault).
    Run in a child process so that a crash fails the test instead of killing it."""
    chunks = (Path(__file__).parents[1] / "data/sleap/cam1.analysis.h5").read_bytes().split(b"\n")
    damaged = tmp_path / "cam1.analysis.h5"
    damaged.write_bytes(b"\n".join(chunks[:5] + chunks[4:]))
    out = tmp_path / "tracks.csv"
    done = subprocess.run(
        [sys.executable, "-m", "dynrecon", "-q", "import-tracks", str(damaged), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"dynrecon import-tracks: error: {damaged}: not a readable HDF5 file: damaged or truncated (export it again "
        "(DeepLabCut's .h5 or CSV, or SLEAP's analysis HDF5))"
    ]
    assert not out.exists()


def test_a_real_multi_animal_labels_file(tmp_path: Path, caplog) -> None:
    """DeepLabCut's own labeled-data CSV (tests/data/dlc): 7 pups of which 2 are labelled, and the unique bodyparts."""
    path = Path(__file__).resolve().parents[1] / "data" / "dlc" / "CollectedData_JohnDoe.csv"
    with caplog.at_level(logging.WARNING):
        named = rows(run_import([path], tmp_path / "a.csv", ImportOptions(video="cam1")))
    assert "2 individuals seen (pup1, pup2)" in caplog.text
    assert {f for _, f, _ in named} == {144, 838, 39580}  # from the image names
    assert named["cam1", 838, "pup1_pup_snout"][:2] == (148.48, 155.2606635)
    assert named["cam1", 144, "nest"][:2] == (892.5866667, 385.5924171)  # the `single` individual: bare names
    every = rows(run_import([path], tmp_path / "b.csv", ImportOptions(video="cam1", every_person=True)))
    # pup1 (8 points) is person 0, pup2 (2 points) person 1
    assert sum(p.startswith("person0_") for _, _, p in every) == 8
    assert sum(p.startswith("person1_") for _, _, p in every) == 2
    assert len(every) == len(named) == 28


def test_many_guesses_are_pointed_out(tmp_path: Path, caplog) -> None:
    """DeepLabCut writes every body part on every frame: where many are low-confidence guesses the import says so,
    and names --min-score; with it, nothing is said."""
    rng = np.random.default_rng(2)
    values = rng.uniform(0, 100, (40, 6))
    values[:, 2::3] = np.where(np.arange(40)[:, None] < 15, 0.05, 0.95)  # 15 of 40 frames are guesses
    csv = tmp_path / "cam1DLC_resnet50.csv"
    dlc_frame(None, ["nose", "tail"], values).to_csv(csv)
    run_import([csv], tmp_path / "tracks.csv", ImportOptions())
    assert "under 0.5" in caplog.text and "--min-score 0.6" in caplog.text
    caplog.clear()
    run_import([csv], tmp_path / "tracks2.csv", ImportOptions(min_score=0.6))
    assert "under 0.5" not in caplog.text


def test_files_that_are_not_deeplabcut_points_say_what_they_are(tmp_path: Path) -> None:
    """A JABS pose file (HDF5, no pandas table) and DeepLabCut's own skeleton CSV (bone lengths): one-line errors
    that say what the file looks like, not "keys: none" or a bare header complaint."""
    import h5py

    jabs = tmp_path / "example_pose_est_v2.h5"
    with h5py.File(jabs, "w") as f:
        f.create_dataset("poseest/points", data=np.zeros((3, 12, 2), dtype=np.uint16))
    with pytest.raises(InputError, match=r"no pandas table; top level: poseest \(a JABS pose file\?\)"):
        run_import([jabs], tmp_path / "o.csv", ImportOptions())
    skeleton = tmp_path / "briefDeepCut_resnet50_TESTAug16shuffle1_5_skeleton.csv"
    skeleton.write_text(",b1_b2,b1_b2,b1_b2\n,length,likelihood,orientation\n0,24.1,0.65,26.3\n", encoding="utf-8")
    with pytest.raises(InputError, match="it is DeepLabCut's skeleton file"):
        run_import([skeleton], tmp_path / "o.csv", ImportOptions())
