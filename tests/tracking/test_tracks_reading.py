"""tracks.csv: the column-wise reader of plain files gives what the row-by-row reader gives, and leaves every
irregular or invalid file to it (so errors still name their line)."""

import numpy as np
import pytest

from dynrecon.errors import InputError
from tracking.tracks import _read_checked, _read_regular, read_tracks

HEADER = "video,frame,point,x,y"
ROWS = ["cam0,0,a,1.5,2.25", "cam0,0,b,-0.0,1e-5", "cam1,3,a,640,480.125", "cam1,4,a,1e2,+7"]


def _same(a, b):
    assert a.video == b.video and a.point == b.point and a.extra == b.extra and a.path == b.path
    for name in ("frame", "xy", "line"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def _outcome(path):
    try:
        return read_tracks(path), None
    except InputError as error:
        return None, str(error)


def _checked(path):
    try:
        return _read_checked(path), None
    except InputError as error:
        return None, str(error)


@pytest.mark.parametrize(
    ("text", "regular"),
    [
        ("\n".join([HEADER, *ROWS]) + "\n", True),
        ("\n".join([HEADER, *ROWS]), True),  # no final line end
        (HEADER + "\n", True),  # no rows
        ("\ufeff" + "\n".join([HEADER, *ROWS]) + "\n", True),  # BOM
        ("\n".join([" video , frame,point,x,y,score,", *(r + ",0.5, z" for r in ROWS)]) + "\n", True),  # extras
        ("\n".join([HEADER, " cam0 , 0 , a ,1,2"]) + "\n", True),  # spaces around names and numbers
        ("\r\n".join([HEADER, *ROWS]) + "\r\n", False),  # CRLF
        ("\n".join([HEADER, *ROWS[:2], "", *ROWS[2:]]) + "\n", False),  # blank line
        ("\n".join([HEADER, *ROWS[:2], " , , , , ", *ROWS[2:]]) + "\n", False),  # whitespace row
        ("\n".join([HEADER, '"cam,0",0,a,1,2', *ROWS]) + "\n", False),  # quoted cell
        ("\n".join([HEADER, *ROWS, "cam2,1,a,1,2,extra"]) + "\n", False),  # a longer row
        ("\n".join([HEADER, *ROWS, "cam2,1,a,1"]) + "\n", False),  # a shorter row
        ("\n".join([HEADER, *ROWS, ROWS[0]]) + "\n", False),  # duplicate
        ("\n".join([HEADER, *ROWS, "cam2,1,a,nan,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, "cam2,1,a,inf,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, "cam2,1,a,x,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, "cam2,-1,a,1,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, "cam2,2147483648,a,1,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, "cam2," + "9" * 5000 + ",a,1,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, "cam2,1.5,a,1,2"]) + "\n", False),
        ("\n".join([HEADER, *ROWS, ",1,a,1,2"]) + "\n", False),  # empty video
        ("\n".join(["video,frame,point,x", *(r.rsplit(",", 1)[0] for r in ROWS)]) + "\n", False),  # no y
        ("", False),
        ("\n", False),
        ("\n".join([HEADER, "cam0,0,a,1,2\x00"]) + "\n", False),
    ],
)
def test_plain_files_read_column_wise_and_others_row_by_row(tmp_path, text, regular):
    path = tmp_path / "tracks.csv"
    path.write_bytes(text.encode())
    assert (_read_regular(path) is not None) == regular
    tracks, error = _outcome(path)
    expected, expected_error = _checked(path)
    assert error == expected_error
    if expected is not None:
        _same(tracks, expected)


def test_cells_beyond_csvs_field_limit_are_left_to_csv(tmp_path):
    path = tmp_path / "tracks.csv"
    path.write_text("\n".join([HEADER, "c" * 200_000 + ",0,a,1,2"]) + "\n")
    assert _read_regular(path) is None
    with pytest.raises(InputError, match="field"):
        read_tracks(path)


def test_a_large_plain_file_reads_the_same_both_ways(tmp_path):
    rng = np.random.default_rng(0)
    lines = [HEADER]
    for f in range(300):
        for p in range(20):
            if rng.random() < 0.8:
                lines.append(f"cam{f % 3},{f},p{p},{rng.normal() * 1000!r},{rng.normal() * 1000!r}")
    path = tmp_path / "tracks.csv"
    path.write_text("\n".join(lines) + "\n")
    assert _read_regular(path) is not None
    _same(read_tracks(path), _read_checked(path))
