from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynrecon.errors import InputError
from reconstruct.outputs.mocap import Mocap, drop_incomplete, read_mocap, select_window, write_trc


def _synthetic(frames: int = 20, markers: int = 3, seed: int = 0) -> Mocap:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-1000, 1000, size=(frames, markers, 3))
    return Mocap(
        xyz=xyz, rate=100.0, marker_names=[f"m{i}" for i in range(markers)], times=0.5 + np.arange(frames) / 100.0
    )


def test_every_shared_file_reads(shared_dir: Path) -> None:
    folder = shared_dir / "data" / "mocap"
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".c3d", ".trc"))
    assert len(files) > 10
    for path in files:
        mocap = read_mocap(path)
        assert mocap.xyz.ndim == 3 and mocap.xyz.shape[2] == 3, path
        assert mocap.xyz.shape[1] == len(mocap.marker_names) == len(set(mocap.marker_names)), path
        assert mocap.rate in (100.0, 120.0, 200.0, 240.0, 250.0, 300.0), path
        assert np.allclose(np.diff(mocap.times), 1 / mocap.rate), path
        known = mocap.xyz[~mocap.missing()]
        assert known.size > 0 and not (known == 0).all(axis=1).any(), path  # zero gaps were masked
        # Every file holds a human-sized subject: the extent of one frame is 0.3 to 3 m, i.e. millimetres.
        frame = int(np.argmin(mocap.missing().sum(axis=1)))
        extent = np.nanmax(mocap.xyz[frame], axis=0) - np.nanmin(mocap.xyz[frame], axis=0)
        assert 300 < extent.max() < 3000, (path, extent)


def test_hdm05_matches_the_paper(shared_dir: Path) -> None:
    mocap = read_mocap(shared_dir / "data/mocap/hdm05/HDM_dg_06-03_03_120.c3d")
    assert mocap.xyz.shape == (202, 44, 3)
    assert mocap.rate == 120.0
    assert not mocap.missing().any()


def test_trc_round_trip_in_metres_and_millimetres(tmp_path: Path) -> None:
    mocap = _synthetic()
    mocap.xyz[3, 1] = np.nan
    for units in ("mm", "m"):
        path = write_trc(tmp_path / f"walk_{units}.trc", mocap, units=units)
        back = read_mocap(path)
        assert back.marker_names == mocap.marker_names
        assert back.rate == 100.0
        np.testing.assert_allclose(back.times, mocap.times, atol=1e-12)
        np.testing.assert_allclose(back.xyz, mocap.xyz, rtol=1e-12, atol=1e-9)  # NaN in the same places
        assert back.missing().sum() == 1


def test_trc_zero_samples_are_missing(tmp_path: Path) -> None:
    mocap = _synthetic()
    path = write_trc(tmp_path / "z.trc", mocap)
    lines = path.read_text().splitlines()
    cells = lines[7].split("\t")  # line 6 is blank, line 7 holds the second frame
    cells[2:5] = ["0", "0", "0"]  # first marker
    lines[7] = "\t".join(cells)
    path.write_text("\n".join(lines) + "\n")
    back = read_mocap(path)
    assert back.missing()[1, 0] and back.missing().sum() == 1


def test_trc_with_padded_header_and_crlf(tmp_path: Path) -> None:
    # Windows exports: CRLF line ends, header values separated by double tabs, names two tabs apart.
    text = (
        "PathFileType  4\t(X/Y/Z) C:\\x\r\n"
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\r\n"
        "  50.0\t\t  50.0\t\t 2\t\t 2\t\t mm\r\n"
        "Frame#\tTime\t\tA\t\tB\r\n"
        "\t\t\tX1\tY1\tZ1\tX2\tY2\tZ2\r\n"
        "1\t0.0\t1\t2\t3\t4\t5\t6\t\r\n"
        "2\t0.02\t7\t8\t9\t\t\t\t\r\n"
    )
    path = tmp_path / "win.trc"
    path.write_bytes(text.encode())
    back = read_mocap(path)
    assert back.rate == 50.0 and back.marker_names == ["A", "B"]
    np.testing.assert_array_equal(back.xyz[0], [[1, 2, 3], [4, 5, 6]])
    assert back.missing().tolist() == [[False, False], [False, True]]


def test_a_comma_separated_trc_reads_as_its_tab_separated_twin(tmp_path: Path) -> None:
    # pyomeca's test files: the OpenSim layout with commas, padded with empty columns to the data's width
    mocap = _synthetic(frames=5, markers=2)
    tabbed = write_trc(tmp_path / "tabs.trc", mocap)
    lines = tabbed.read_text().splitlines()
    width = 2 + 3 * 2
    commas = [",".join((line.split("\t") + [""] * width)[: max(width, len(line.split("\t")))]) for line in lines]
    path = tmp_path / "commas.trc"
    path.write_text("\n".join(commas) + "\n")
    back = read_mocap(path)
    assert back.rate == 100.0 and back.marker_names == mocap.marker_names
    np.testing.assert_allclose(back.xyz, mocap.xyz, rtol=1e-12)
    np.testing.assert_allclose(back.times, mocap.times, atol=1e-12)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("motion.bvh", "HIERARCHY", "unknown motion-capture format"),
        ("short.trc", "PathFileType\t4\n", "5 header lines"),
        (
            "nomarkers.trc",
            "P\nDataRate\tNumFrames\tNumMarkers\tUnits\n100\t1\t0\tmm\nFrame#\tTime\n\t\n1\t0\n",
            "no markers",
        ),
        (
            "units.trc",
            "P\nDataRate\tNumFrames\tNumMarkers\tUnits\n100\t1\t1\tinch\nFrame#\tTime\tA\n\t\tX1\n1\t0\t1\t2\t3\n",
            "unknown Units",
        ),
        ("bad.c3d", "not a c3d file at all", "not a readable C3D file"),
    ],
)
def test_bad_files_are_one_line_errors(tmp_path: Path, name: str, content: str, message: str) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError, match=message) as error:
        read_mocap(path)
    assert "\n" not in str(error.value) and str(path) in str(error.value)


def test_an_absurd_coordinate_names_its_line(tmp_path: Path) -> None:
    path = write_trc(tmp_path / "t.trc", _synthetic())
    lines = path.read_text().splitlines()
    fields = lines[7].split("\t")
    fields[2], fields[3] = "", "1e300"  # after a gap in the same row
    lines[7] = "\t".join(fields)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"t\.trc:line 8: coordinate 1e\+300 mm is implausible"):
        read_mocap(path)


def test_truncated_trc_names_the_line(tmp_path: Path) -> None:
    path = write_trc(tmp_path / "t.trc", _synthetic())
    text = path.read_text()
    path.write_text(text[: len(text) - 30])  # cut inside the last row
    with pytest.raises(InputError, match=r"t\.trc:line 26: expected 11"):
        read_mocap(path)
    lines = text.splitlines()
    path.write_text("\n".join(lines[:-3]) + "\n")  # whole rows missing
    with pytest.raises(InputError, match="NumFrames is 20 but only 17"):
        read_mocap(path)


def test_truncated_c3d(tmp_path: Path, shared_dir: Path) -> None:
    data = (shared_dir / "data/mocap/hdm05/HDM_dg_06-03_03_120.c3d").read_bytes()
    path = tmp_path / "cut.c3d"
    path.write_bytes(data[:600])
    with pytest.raises(InputError, match=r"cut\.c3d"):
        read_mocap(path)
    path.write_bytes(data[: len(data) // 2])  # whole frames missing: ezc3d reads the rest without a word
    with pytest.raises(InputError, match=r"cut\.c3d: its header declares 202 frames but only \d+ could be read"):
        read_mocap(path)


def test_select_window_keeps_times() -> None:
    mocap = _synthetic(frames=30)
    window = select_window(mocap, start=4, length=10, step=3)
    np.testing.assert_array_equal(window.xyz, mocap.xyz[[4, 7, 10, 13]])
    np.testing.assert_allclose(window.times, mocap.times[[4, 7, 10, 13]])
    assert window.rate == mocap.rate
    assert select_window(mocap).num_frames == 30
    with pytest.raises(InputError, match="outside"):
        select_window(mocap, start=30)
    with pytest.raises(InputError, match="step"):
        select_window(mocap, step=0)


def test_drop_incomplete() -> None:
    mocap = _synthetic(frames=20, markers=4)
    mocap.xyz[:5, 0] = np.nan  # 25 % missing: dropped at 10 %
    mocap.xyz[7, 2] = np.nan  # 5 % missing: kept, frame 7 dropped
    clean = drop_incomplete(mocap, max_missing=0.1)
    assert clean.marker_names == ["m1", "m2", "m3"]
    assert clean.num_frames == 19 and 7 not in np.round((clean.times - 0.5) * 100).astype(int)
    assert not clean.missing().any()
    mocap.xyz[np.arange(4), np.arange(4)] = np.nan  # now every marker misses at least one frame
    with pytest.raises(InputError, match="every marker"):
        drop_incomplete(mocap, max_missing=0.0)


def test_a_file_complete_only_in_its_middle_names_that_stretch() -> None:
    from reconstruct.outputs.mocap import complete_span

    mocap = _synthetic(frames=30)
    mocap.xyz[:12, 1:] = np.nan  # markers 1 and 2 only from frame 12 to 25
    mocap.xyz[26:, 1:] = np.nan
    mocap.xyz[:6, 0] = np.nan  # every marker missing in over 10 % of the frames
    assert complete_span(mocap) == (12, 25)
    with pytest.raises(InputError, match=r"present together in frames 12\.\.25 of the file: --start 12 --length 14"):
        drop_incomplete(mocap, max_missing=0.1, whole=mocap)


def test_dropping_most_markers_says_how_to_keep_them(caplog: pytest.LogCaptureFixture) -> None:
    """A Plug-in Gait file kept 3 of its 54 markers (the rest missing in over 10 % of the frames) and was scored at
    100 %: the warning says how to keep more (--max-missing, or the window where they are present together)."""
    mocap = _synthetic(frames=30, markers=4)
    mocap.xyz[:6, 1:] = np.nan  # three of four markers missing in 20 % of the frames
    clean = drop_incomplete(mocap, max_missing=0.1, whole=mocap)
    assert clean.marker_names == ["m0"]
    assert "dropped 3 of 4 markers" in caplog.text
    assert "(to keep more: --max-missing, or a window: the markers are present together in frames 6..29" in caplog.text
    caplog.clear()
    mocap.xyz[:, 1:] = _synthetic(frames=30, markers=4).xyz[:, 1:]
    mocap.xyz[:6, 3] = np.nan  # one of four: said, without the advice
    drop_incomplete(mocap, max_missing=0.1, whole=mocap)
    assert "dropped 1 of 4 markers" in caplog.text and "to keep more" not in caplog.text


def _smooth(frames: int, markers: int) -> np.ndarray:
    """(T, M, 3) mm: markers circling at walking speed."""
    t = np.arange(frames)[:, None] / 100
    phase = np.arange(markers)[None, :]
    return np.stack([500 * np.cos(2 * t + phase), 500 * np.sin(2 * t + phase), 900 + 10 * phase + 0 * t], axis=2)


def _write_c3d(
    path: Path, xyz: np.ndarray, labels: list[str], units: str = "mm", rate: int = 100, **groups: list[str]
) -> Path:
    """A C3D as ezc3d writes it: `xyz` (T, M, 3) in `units`, POINT:LABELS, and label groups such as ANGLES."""
    import ezc3d

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = [units]
    for key, names in groups.items():
        c3d.add_parameter("POINT", key, names)
    points = np.ones((4, *xyz.shape[1::-1]))
    points[:3] = xyz.transpose(2, 1, 0)
    c3d["data"]["points"] = points
    c3d.write(str(path))
    return path


def test_model_outputs_stored_as_points_are_not_markers(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Vicon Plug-in Gait stores joint angles (degrees), forces, moments and powers as points, listed in POINT:ANGLES,
    FORCES, MOMENTS, POWERS: simulated as markers they were scored as the worst 'markers' of a walk."""
    xyz = _smooth(frames=30, markers=4)
    labels = ["LASI", "RASI", "LKneeAngles", "LAnkleMoment"]
    path = _write_c3d(tmp_path / "pig.c3d", xyz, labels, ANGLES=["LKneeAngles"], MOMENTS=["LAnkleMoment"])
    mocap = read_mocap(path)
    assert mocap.marker_names == ["LASI", "RASI"]
    np.testing.assert_allclose(mocap.xyz, xyz[:, :2], atol=1e-3)
    assert "2 of its 4 points are model outputs" in caplog.text


def test_units_cut_short_by_the_writer_are_read(tmp_path: Path) -> None:
    """Some writers keep 4 characters of the units ('mete'): metres, not an unknown unit."""
    xyz = _smooth(frames=10, markers=2) / 1000
    assert np.allclose(read_mocap(_write_c3d(tmp_path / "m.c3d", xyz, ["a", "b"], units="mete")).xyz, xyz * 1000)
    assert np.allclose(
        read_mocap(_write_c3d(tmp_path / "c.c3d", xyz * 100, ["a", "b"], units="centimeters")).xyz, xyz * 1000
    )
    with pytest.raises(InputError, match="unknown POINT:UNITS 'me'"):
        read_mocap(_write_c3d(tmp_path / "me.c3d", xyz, ["a", "b"], units="me"))


def test_frames_read_out_of_order_are_refused(tmp_path: Path) -> None:
    """A C3D whose data section the reader misplaces gives every other frame as garbage (c3d.org's sample28 and a
    Vicon Workstation file, a standing trial at a median 45 m/s): refused, not simulated as a motion."""
    xyz = _smooth(frames=40, markers=5)
    garbage = xyz.copy()
    garbage[1::2] = np.random.default_rng(1).uniform(-3000, 3000, garbage[1::2].shape)
    with pytest.raises(InputError, match="jump back and forth between frames"):
        read_mocap(_write_c3d(tmp_path / "misread.c3d", garbage, list("abcde")))
    # a fast single object (a ball at 30 m/s) moves smoothly: read
    t = np.arange(40)[:, None] / 100
    ball = np.concatenate([30_000 * t, 2_000 * t, 1_000 - 4_900 * t**2], axis=1)[:, None, :] + 1.0
    assert read_mocap(_write_c3d(tmp_path / "ball.c3d", ball, ["ball"])).num_markers == 1
    # a standing trial's noise (white: second differences about 3.5 times half the two-frame step) at 1 kHz: read
    still = 1000 + np.random.default_rng(2).normal(0, 5, (200, 3, 3))
    assert read_mocap(_write_c3d(tmp_path / "still.c3d", still, ["a", "b", "c"], rate=1000)).num_frames == 200
