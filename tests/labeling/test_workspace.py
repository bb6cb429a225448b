"""labeling.json, skeleton files, --points and video discovery."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dynrecon.errors import InputError
from labeling.skeleton import Skeleton, parse_points, read_skeleton
from labeling.workspace import WorkspaceConfig, load_config, resolve_videos, save_config
from tracking.workspace import workspace_videos


def test_points_option() -> None:
    assert parse_points(" head, hip ,head,,knee").points == ["head", "hip", "knee"]
    with pytest.raises(InputError, match="invalid point name"):
        parse_points('a,b"c')


def test_skeleton_connections_add_their_points(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"points": ["a"], "connections": [["a", "b"], ["b", "c"]]}))
    skeleton = read_skeleton(path)
    assert skeleton.points == ["a", "b", "c"]
    assert skeleton.connections == [("a", "b"), ("b", "c")]


@pytest.mark.parametrize(
    "content", ["[1]", "{", '{"points": "a"}', '{"connections": [["a"]]}', '{"connections": [["a", 3]]}']
)
def test_bad_skeleton_files(tmp_path: Path, content: str) -> None:
    path = tmp_path / "s.json"
    path.write_text(content)
    with pytest.raises(InputError) as caught:
        read_skeleton(path)
    assert str(path) in str(caught.value)


def test_config_round_trip_keeps_workspace_paths_relative(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    (ws / "videos").mkdir(parents=True)
    inside, outside = ws / "videos" / "a.mp4", tmp_path / "b.mp4"
    inside.write_bytes(b"")
    outside.write_bytes(b"")
    config = WorkspaceConfig(
        videos={"a": inside, "b": outside}, skeleton=Skeleton(points=["x", "y"], connections=[("x", "y")])
    )
    save_config(ws, config)
    data = json.loads((ws / "labeling.json").read_text())
    assert data["videos"] == {"a": "videos/a.mp4", "b": str(outside.resolve())}
    loaded = load_config(ws)
    assert loaded.videos == {"a": ws / "videos" / "a.mp4", "b": outside.resolve()}
    assert loaded.skeleton == config.skeleton
    # The tracking stage finds the same videos from the same file.
    assert workspace_videos(ws) == loaded.videos


def test_skeleton_merge_and_rename() -> None:
    skeleton = Skeleton(points=["a", "b"], connections=[("a", "b")])
    skeleton.merge(Skeleton(points=["c"], connections=[("b", "a"), ("b", "c")]))
    assert skeleton.points == ["a", "b", "c"] and skeleton.connections == [("a", "b"), ("b", "c")]
    skeleton.rename("b", "z")
    assert skeleton.points == ["a", "z", "c"] and skeleton.connections == [("a", "z"), ("z", "c")]


def test_resolve_videos_order_and_errors(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    (ws / "videos").mkdir(parents=True)
    for name in ("b.mp4", "a.avi", "notes.txt"):
        (ws / "videos" / name).write_bytes(b"")
    assert list(resolve_videos(ws, None, {})) == ["a", "b"]
    remembered = {"r": ws / "videos" / "b.mp4"}
    assert list(resolve_videos(ws, None, remembered)) == ["b"]
    (tmp_path / "b.mp4").write_bytes(b"")
    with pytest.raises(InputError, match="two videos are named 'b'"):
        resolve_videos(ws, [ws / "videos" / "b.mp4", tmp_path / "b.mp4"], {})
    with pytest.raises(InputError, match="video file not found"):
        resolve_videos(ws, [tmp_path / "missing.mp4"], {})
    with pytest.raises(InputError, match="no videos"):
        resolve_videos(tmp_path / "empty", None, {})
