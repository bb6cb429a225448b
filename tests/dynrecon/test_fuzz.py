"""Generated hostile input for the contract readers: each returns a valid result or raises a one-line DynreconError,
never another exception (issue 18). Small budgets (`max_examples`), so the whole file runs in seconds."""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dynrecon.errors import DynreconError
from reconstruct.outputs.points import read_sequencing
from sfm.cameras import read_cameras
from tracking.labels import read_labels
from tracking.tracks import read_tracks

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# Cells that have broken readers before: huge, non-finite, quoted, empty, odd whitespace and line ends.
TRICKY_CELLS = [
    "",
    " ",
    "0",
    "-1",
    "1.5",
    "nan",
    "inf",
    "-inf",
    "1e308",
    "1e309",
    "-0",
    str(2**31),
    str(2**63),
    "9" * 5000,
    "٣",
    '"',
    '""',
    '"a,b"',
    "\r",
    "\n",
    "\ufeff",
    "\x00",
    "a",
    "label",
    "hidden",
    "cam0",
    "..",
]
cells = st.one_of(st.sampled_from(TRICKY_CELLS), st.text(max_size=8))
row = st.lists(cells, min_size=0, max_size=8).map(",".join)
line_end = st.sampled_from(["\n", "\r\n", "\r"])


@st.composite
def csv_text(draw: st.DrawFn, header: str) -> str:
    """A header (sometimes with a BOM, sometimes broken) and rows of tricky cells."""
    head = draw(st.sampled_from([header, "\ufeff" + header, header.upper(), header.replace(",", ";"), ""]))
    rows = draw(st.lists(row, max_size=12))
    end = draw(line_end)
    return end.join([head, *rows]) + draw(st.sampled_from(["", end]))


def _check(reader: Callable[[Path], Any], data: str | bytes, name: str) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / name
        if isinstance(data, str):
            path.write_text(data, encoding="utf-8", newline="")
        else:
            path.write_bytes(data)
        try:
            reader(path)
        except DynreconError as error:
            message = str(error)
            assert "\n" not in message and "\r" not in message, message
            assert len(message) < 1000, message


# ---- tracks.csv


@FUZZ
@given(csv_text("video,frame,point,x,y"))
def test_tracks_csv_text(text: str) -> None:
    _check(read_tracks, text, "tracks.csv")


@FUZZ
@given(st.binary(max_size=200).map(lambda b: b"video,frame,point,x,y\n" + b))
def test_tracks_csv_bytes(data: bytes) -> None:
    _check(read_tracks, data, "tracks.csv")


@FUZZ
@given(csv_text("video,frame,point,x,y"))
def test_tracks_csv_valid_result(text: str) -> None:
    # Whatever reads back is a valid set of observations: finite, frames in range, one row per key.
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "tracks.csv"
        path.write_text(text, encoding="utf-8", newline="")
        try:
            tracks = read_tracks(path)
        except DynreconError:
            return
    assert np.all(np.isfinite(tracks.xy)) and np.all((tracks.frame >= 0) & (tracks.frame < 2**31))
    keys = list(zip(tracks.video, tracks.frame.tolist(), tracks.point, strict=True))
    assert len(set(keys)) == len(keys) and all(v.strip() and p.strip() for v, _, p in keys)


# ---- labels.csv


@FUZZ
@given(csv_text("video,frame,point,x,y,source"))
def test_labels_csv_text(text: str) -> None:
    _check(read_labels, text, "labels.csv")


@FUZZ
@given(st.binary(max_size=200).map(lambda b: b"video,frame,point,x,y,source\n" + b))
def test_labels_csv_bytes(data: bytes) -> None:
    _check(read_labels, data, "labels.csv")


# ---- cameras.json

numbers = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, 1, -1, 1e-300, 1e308, 2**63, 0.5]),
)
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=6)),
    lambda children: st.one_of(
        st.lists(children, max_size=4), st.dictionaries(st.text(max_size=5), children, max_size=4)
    ),
    max_leaves=12,
)


def _matrix(rows: int, cols: int) -> st.SearchStrategy[list]:
    return st.lists(st.lists(numbers, min_size=cols, max_size=cols), min_size=rows, max_size=rows)


@st.composite
def camera_documents(draw: st.DrawFn) -> Any:
    """Mostly well-formed cameras.json with hostile values in every field; sometimes any JSON at all."""
    if draw(st.booleans()):
        return draw(json_values)
    frame = {
        "frame": draw(st.one_of(st.integers(min_value=-2, max_value=2**64), numbers, json_values)),
        "K": draw(st.one_of(st.just([[100, 0, 50], [0, 100, 50], [0, 0, 1]]), _matrix(3, 3), json_values)),
        "R": draw(st.one_of(st.just(np.eye(3).tolist()), _matrix(3, 3), json_values)),
        "t": draw(st.one_of(st.lists(numbers, min_size=3, max_size=3), json_values)),
    }
    if draw(st.booleans()):
        frame["dist"] = draw(st.one_of(st.lists(numbers, min_size=4, max_size=5), json_values))
    if draw(st.booleans()):
        frame["time"] = draw(st.one_of(numbers, json_values))
    video = {
        "name": draw(st.one_of(st.just("a"), st.text(max_size=4), json_values)),
        "width": draw(st.one_of(st.just(100), numbers)),
        "height": draw(st.one_of(st.just(100), numbers)),
        "fps": draw(st.one_of(st.none(), numbers)),
        "frames": [frame],
    }
    return {"videos": [video]}


@FUZZ
@given(camera_documents())
def test_cameras_json_documents(document: Any) -> None:
    _check(read_cameras, json.dumps(document), "cameras.json")


@FUZZ
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_cameras_json_any_text(data: str | bytes) -> None:
    _check(read_cameras, data, "cameras.json")


# ---- sequencing.json


@st.composite
def sequencing_documents(draw: st.DrawFn) -> Any:
    if draw(st.booleans()):
        return draw(json_values)
    names = ["a", "b"]
    weights = st.one_of(numbers, st.sampled_from([math.nan, math.inf, -0.5]), json_values)
    frames = [
        {
            "video": name,
            "frame": draw(st.one_of(st.just(0), numbers)),
            "neighbours": draw(
                st.lists(
                    st.fixed_dictionaries(
                        {"video": st.sampled_from(names), "frame": st.one_of(st.just(0), numbers), "weight": weights}
                    ),
                    max_size=3,
                )
            ),
        }
        for name in names
    ]
    return {"frames": frames}


@FUZZ
@given(sequencing_documents())
def test_sequencing_json_documents(document: Any) -> None:
    _check(read_sequencing, json.dumps(document), "sequencing.json")


@FUZZ
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_sequencing_json_any_text(data: str | bytes) -> None:
    _check(read_sequencing, data, "sequencing.json")
