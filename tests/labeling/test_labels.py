"""labels.csv: round trip, hidden marks, line-numbered errors, serialized writes, read by the tracker."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from dynrecon.errors import InputError
from labeling import labels as labels_module
from labeling.labels import Change, LabelStore
from tracking.labels import Label, Source, read_labels, write_labels
from tracking.workspace import read_labels as tracker_read_labels

LABELS = {
    ("cam2", 5, "hip"): Label(source=Source.LABEL, xy=(10.125, 20.5)),
    ("cam1", 7, "knee"): Label(source=Source.HIDDEN),
    ("cam1", 7, "hip"): Label(source=Source.LABEL, xy=(-0.5, 1079.5)),
    ("cam1", 0, "hip"): Label(source=Source.LABEL, xy=(3.0, 4.0)),
}


def test_round_trip_sorted_with_hidden_rows(tmp_path: Path) -> None:
    path = write_labels(tmp_path / "labels.csv", LABELS, point_order=["hip", "knee"])
    assert path.read_text().splitlines() == [
        "video,frame,point,x,y,source",
        "cam1,0,hip,3.000,4.000,label",
        "cam1,7,hip,-0.500,1079.500,label",
        "cam1,7,knee,,,hidden",
        "cam2,5,hip,10.125,20.500,label",
    ]
    assert read_labels(path) == LABELS


def test_the_tracker_reads_what_the_page_writes(tmp_path: Path) -> None:
    path = write_labels(tmp_path / "labels.csv", LABELS)
    assert tracker_read_labels(path) == {
        "cam1": {"hip": {0: (3.0, 4.0), 7: (-0.5, 1079.5)}, "knee": {7: None}},
        "cam2": {"hip": {5: (10.125, 20.5)}},
    }


def test_missing_or_empty_file_is_no_labels(tmp_path: Path) -> None:
    assert read_labels(tmp_path / "none.csv") == {}
    (tmp_path / "empty.csv").write_text("")
    assert read_labels(tmp_path / "empty.csv") == {}


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("cam1,x,hip,1,2,label", "line 3: frame 'x' is not an integer"),
        ("cam1,-1,hip,1,2,label", "line 3: frame -1 is negative"),
        ("cam1,1,hip,,,label", "line 3: x, y = '', '' are not numbers"),
        ("cam1,1,hip,nan,2,label", "line 3: x, y = nan, 2.0 is not finite"),
        ("cam1,1,hip,1,2,guess", "line 3: source 'guess'"),
        (",1,hip,1,2,label", "line 3: empty video or point name"),
        ("cam1,1,hip,1", "line 3: expected 6 fields, found 4"),
    ],
)
def test_errors_name_file_and_line(tmp_path: Path, row: str, message: str) -> None:
    path = tmp_path / "labels.csv"
    path.write_text(f"video,frame,point,x,y,source\ncam1,0,hip,1,2,label\n{row}\n")
    with pytest.raises(InputError, match=message) as caught:
        read_labels(path)
    assert str(path) in str(caught.value)


def test_header_without_columns_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    path.write_text("video,frame,x,y\n")
    with pytest.raises(InputError, match="lacks column"):
        read_labels(path)


def test_concurrent_changes_are_all_kept(tmp_path: Path) -> None:
    store = LabelStore(tmp_path / "labels.csv")

    def click(i: int) -> None:
        store.apply([Change(key=("cam1", i, "hip"), label=Label(source=Source.LABEL, xy=(i, i)))])

    threads = [threading.Thread(target=click, args=(i,)) for i in range(24)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert set(read_labels(tmp_path / "labels.csv")) == {("cam1", i, "hip") for i in range(24)}


def test_a_failed_write_keeps_file_and_memory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "labels.csv"
    store = LabelStore(path)
    store.apply([Change(key=("cam1", 0, "hip"), label=Label(source=Source.LABEL, xy=(1, 2)))])
    before = path.read_bytes()

    def disk_full(*args: object, **kwargs: object) -> Path:
        raise OSError("No space left on device")

    monkeypatch.setattr(labels_module, "write_labels", disk_full)
    with pytest.raises(OSError, match="No space"):
        store.apply([Change(key=("cam1", 1, "hip"), label=Label(source=Source.LABEL, xy=(3, 4)))])
    assert path.read_bytes() == before
    assert set(store.snapshot()) == {("cam1", 0, "hip")}


def test_rename_refuses_to_merge_points(tmp_path: Path) -> None:
    store = LabelStore(tmp_path / "labels.csv")
    store.apply(
        [
            Change(key=("cam1", 0, "a"), label=Label(source=Source.LABEL, xy=(1, 2))),
            Change(key=("cam1", 0, "b"), label=Label(source=Source.HIDDEN)),
        ]
    )
    with pytest.raises(ValueError, match="already has labels"):
        store.rename_point("a", "b")
    assert store.rename_point("a", "c") == 1
    assert set(read_labels(tmp_path / "labels.csv")) == {("cam1", 0, "c"), ("cam1", 0, "b")}


def test_duplicate_rows_are_an_error_naming_both_lines(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    path.write_text("video,frame,point,x,y,source\na,0,p,1,2,label\na,1,p,1,2,label\na,0,p,3,4,label\n")
    with pytest.raises(InputError, match=r"line 4: .* labeled twice on frame 0 \(first on line 2\)"):
        read_labels(path)
