"""labels.csv: round trip, hidden marks, line-numbered errors, serialized writes, read by the tracker."""

from __future__ import annotations

import errno
import os
import threading
import time
from pathlib import Path

import pytest

from dynrecon import atomic
from dynrecon.errors import InputError
from labeling import labels as labels_module
from labeling.labels import Change, LabelStore, SaveError, StoreClosedError
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
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(labels_module, "write_labels", disk_full)
    with pytest.raises(SaveError, match=r"cannot save labels.csv: No space left on device \(free some") as caught:
        store.apply([Change(key=("cam1", 1, "hip"), label=Label(source=Source.LABEL, xy=(3, 4)))])
    assert caught.value.disk_full
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


def click(key: tuple[str, int, str], x: float = 1.0) -> Change:
    return Change(key=key, label=Label(source=Source.LABEL, xy=(x, 2.0)))


@pytest.mark.parametrize("where", ["write", "fsync", "replace", "interrupt", "fdopen"])
def test_a_failed_write_leaves_no_temporary_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    path = tmp_path / "labels.csv"
    store = LabelStore(path)
    store.apply([click(("cam1", 0, "hip"))])
    before = path.read_bytes()

    def fail(*args: object, **kwargs: object) -> None:
        if where == "interrupt":
            raise KeyboardInterrupt
        raise OSError(errno.ENOSPC, "No space left on device")

    if where == "write":
        monkeypatch.setattr(labels_module, "write_labels", _writer_that_fails_midway)
    elif where == "fdopen":
        monkeypatch.setattr(atomic.os, "fdopen", fail)
    else:
        monkeypatch.setattr(atomic.os, "replace" if where == "replace" else "fsync", fail)
    with pytest.raises(KeyboardInterrupt if where == "interrupt" else SaveError):
        store.apply([click(("cam1", 1, "hip"))])
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert atomic.temp_files(path) == []
    assert sorted(os.listdir(tmp_path)) == ["labels.csv"]


def _writer_that_fails_midway(path: Path, labels: object, point_order: object = None) -> Path:
    with atomic.atomic_open(path, "w") as handle:
        handle.write("video,frame,point,x,y,source\n")
        raise OSError(errno.EROFS, "Read-only file system")


def test_temporary_files_of_a_killed_server_are_removed_at_start(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    write_labels(path, LABELS)
    for name in (".labels.csv.abc123.tmp", ".labels.csv.x.tmp", "..labels.csv.1-2.tmp.abc.tmp"):
        (tmp_path / name).write_text("half a file")
    (tmp_path / ".tracks.csv.abc.tmp").write_text("not ours")
    store = LabelStore(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tracks.csv.abc.tmp", "labels.csv"]
    assert store.snapshot() == LABELS


def test_a_closed_store_refuses_changes(tmp_path: Path) -> None:
    store = LabelStore(tmp_path / "labels.csv")
    store.close()
    with pytest.raises(StoreClosedError):
        store.apply([click(("cam1", 0, "hip"))])
    assert not (tmp_path / "labels.csv").exists()


def test_an_outside_rewrite_from_an_old_copy_loses_no_click(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    store = LabelStore(path)
    store.apply([click(("cam1", 0, "hip"))])
    old_copy = path.read_text()
    store.apply([click(("cam1", 1, "hip"))])
    # A text editor that opened the file before the second click saves its own row.
    path.write_text(old_copy + "cam2,3,knee,5.000,6.000,label\n")
    store.apply([click(("cam1", 2, "hip"))])
    assert set(read_labels(path)) == {("cam1", 0, "hip"), ("cam1", 1, "hip"), ("cam1", 2, "hip"), ("cam2", 3, "knee")}


def test_outside_values_win_and_outside_deletions_of_other_rows_are_kept(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    write_labels(path, {("cam9", 0, "hip"): Label(source=Source.HIDDEN)})
    store = LabelStore(path)
    store.apply([click(("cam1", 0, "hip"))])
    # The outside edit moves the page's label and deletes a row the page never touched.
    path.write_text("video,frame,point,x,y,source\ncam1,0,hip,7.000,8.000,label\n")
    store.apply([click(("cam1", 1, "hip"))])
    labels = read_labels(path)
    assert set(labels) == {("cam1", 0, "hip"), ("cam1", 1, "hip")}
    assert labels[("cam1", 0, "hip")].xy == (7.0, 8.0)


def test_page_deletions_stay_deleted_after_a_merge(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    store = LabelStore(path)
    store.apply([click(("cam1", 0, "hip")), click(("cam1", 1, "hip"))])
    store.apply([Change(key=("cam1", 0, "hip"), label=None)])
    path.write_text(path.read_text() + "cam2,3,knee,5.000,6.000,label\n")
    store.apply([click(("cam1", 2, "hip"))])
    assert set(read_labels(path)) == {("cam1", 1, "hip"), ("cam1", 2, "hip"), ("cam2", 3, "knee")}


def test_a_burst_of_clicks_with_outside_edits_loses_nothing(tmp_path: Path) -> None:
    """~100 clicks/s from several threads while an outside tool rewrites the file from stale copies."""
    path = tmp_path / "labels.csv"
    store = LabelStore(path)
    stop = threading.Event()
    outside_rows: list[tuple[str, int, str]] = []

    def outside() -> None:
        i = 0
        while not stop.is_set():
            stale = path.read_text() if path.exists() else "video,frame,point,x,y,source\n"
            time.sleep(0.01)  # clicks land between the read and the write
            row = ("out", i, "knee")
            # Alternate a plain truncate-and-write (an editor) with an atomic rename (another tool).
            text = stale + f"{row[0]},{row[1]},{row[2]},1.000,1.000,label\n"
            if i % 2:
                path.write_text(text)
            else:
                with atomic.atomic_open(path) as handle:
                    handle.write(text)
            outside_rows.append(row)
            i += 1

    def clicker(t: int) -> None:
        for i in range(25):
            store.apply([click((f"cam{t}", i, "hip"), x=i)])
            time.sleep(0.04)

    editor = threading.Thread(target=outside)
    editor.start()
    clickers = [threading.Thread(target=clicker, args=(t,)) for t in range(4)]
    for thread in clickers:
        thread.start()
    for thread in clickers:
        thread.join()
    stop.set()
    editor.join()
    store.apply([click(("last", 0, "hip"))])  # merges the outside tool's final write
    on_disk = set(read_labels(path))
    clicks = {(f"cam{t}", i, "hip") for t in range(4) for i in range(25)}
    assert clicks <= on_disk, f"lost {len(clicks - on_disk)} clicks"
    assert len(outside_rows) > 3
    assert outside_rows[-1] in on_disk  # the outside edit after the burst is merged, not clobbered
    assert atomic.temp_files(path) == []
