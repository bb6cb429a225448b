from __future__ import annotations

import json
from pathlib import Path

import pytest

from dynrecon.errors import InputError
from tracking.workspace import read_labels, workspace_videos


def test_read_labels_with_hidden_marks(tmp_path: Path) -> None:
    path = tmp_path / "labels.csv"
    path.write_text("video,frame,point,x,y,source\na,0,p,1.5,2.5,label\na,4,p,,,hidden\nb,2,q,3,4,label\n\n")
    assert read_labels(path) == {"a": {"p": {0: (1.5, 2.5), 4: None}}, "b": {"q": {2: (3.0, 4.0)}}}
    assert read_labels(tmp_path / "absent.csv") == {}
    no_source = tmp_path / "plain.csv"
    no_source.write_text("video,frame,point,x,y\na,0,p,1,2\n")
    assert read_labels(no_source) == {"a": {"p": {0: (1.0, 2.0)}}}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("video,frame,point,x\n", "line 1: header lacks column(s) y"),
        (
            "video,frame,point,x,y,source\na,0,p,1,2,label\na,0,p,3,4,label\n",
            "line 3: point 'p' of video 'a' is labeled twice",
        ),
        ("video,frame,point,x,y,source\na,-1,p,1,2,label\n", "line 2: frame -1 is negative"),
        ("video,frame,point,x,y,source\na,0,p,,,label\n", "line 2: x, y = '', '' are not numbers"),
        ("video,frame,point,x,y,source\na,0,p,inf,2,label\n", "line 2: x, y = inf, 2.0 is not finite"),
        ("video,frame,point,x,y,source\na,0,p,1\n", "line 2: expected 6 fields, found 4"),
        ("video,frame,point,x,y,source\n,0,p,1,2,label\n", "line 2: empty video or point name"),
    ],
)
def test_bad_labels_name_the_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "labels.csv"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_labels(path)
    assert message in str(info.value) and str(info.value).startswith(str(path))


def test_workspace_videos_resolution_order(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    (ws / "videos").mkdir(parents=True)
    for name in ("b.mp4", "a.avi", "notes.txt"):
        (ws / "videos" / name).write_bytes(b"x")
    assert workspace_videos(ws) == {"a": ws / "videos" / "a.avi", "b": ws / "videos" / "b.mp4"}
    (ws / "labeling.json").write_text(json.dumps({"videos": {"cam": "videos/b.mp4"}}))
    assert workspace_videos(ws) == {"cam": ws / "videos" / "b.mp4"}
    given = tmp_path / "c.mp4"
    given.write_bytes(b"x")
    assert workspace_videos(ws, [given]) == {"c": given}
    with pytest.raises(InputError, match="two videos are named 'c'"):
        workspace_videos(ws, [given, given])
    (ws / "labeling.json").write_text('{"videos": ["x.mp4"]}')
    with pytest.raises(InputError, match="'videos' must map video names to file paths"):
        workspace_videos(ws)
    (ws / "labeling.json").write_text("{oops")
    with pytest.raises(InputError, match="not valid JSON"):
        workspace_videos(ws)
