"""HTTP tests of the labeling server on an ephemeral port: label round trip, safety (404/400), lock file."""

from __future__ import annotations

import csv
import http.client
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from labeling_videos import FRAMES, HEIGHT, WIDTH

from labeling.lock import LOCK_NAME, WorkspaceLockedError
from labeling.skeleton import Skeleton
from labeling.stage import LabelOptions, LabelServer
from tracking.labels import read_labels
from tracking.tracks import Tracks, write_tracks


def fake_tracker(workspace: Path, videos: dict[str, Path]) -> Path:
    """Stands in for tracking: every label is copied to the next frame with score 0.5."""
    rows, scores = [], []
    for (video, frame, point), label in read_labels(workspace / "labels.csv").items():
        if label.xy is not None and video in videos and frame + 1 < FRAMES:
            rows.append((video, frame + 1, point, label.xy[0] + 1.0, label.xy[1]))
            scores.append("0.5")
    return write_tracks(workspace / "tracks.csv", Tracks.from_rows(rows, source=["track"] * len(rows), score=scores))


def request(
    server: LabelServer, method: str, path: str, body: bytes | str | None = None, headers: dict[str, str] | None = None
) -> tuple[int, bytes]:
    host, port = server.httpd.server_address[:2]
    conn = http.client.HTTPConnection(str(host), int(port), timeout=10)
    if method == "POST":
        headers = {"Content-Type": "application/json", **(headers or {})}
    try:
        conn.request(method, path, body=body, headers=headers or {})
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        conn.close()


def post(server: LabelServer, path: str, obj: object) -> tuple[int, dict]:
    status, data = request(server, "POST", path, json.dumps(obj))
    return status, json.loads(data)


@pytest.fixture
def server(workspace: Path, video: Path):
    options = LabelOptions(videos=[video], skeleton=Skeleton(points=["head", "tail"], connections=[("head", "tail")]))
    with LabelServer(workspace, options, track=fake_tracker) as running:
        yield running


def test_state_lists_videos_points_and_skeleton(server: LabelServer) -> None:
    status, data = request(server, "GET", "/api/state")
    state = json.loads(data)
    assert status == 200
    assert state["videos"] == [{"name": "cam1", "frames": FRAMES, "width": WIDTH, "height": HEIGHT, "fps": 10.0}]
    assert state["points"] == ["head", "tail"]
    assert state["connections"] == [["head", "tail"]]
    assert server.url.startswith("http://127.0.0.1:")


def test_page_and_static_files_are_served(server: LabelServer) -> None:
    status, page = request(server, "GET", "/")
    assert status == 200 and b"<canvas" in page
    for name in ("app.js", "style.css"):
        status, _ = request(server, "GET", f"/static/{name}")
        assert status == 200, name


def test_frame_is_the_decoded_video_frame(server: LabelServer, video: Path) -> None:
    cap = cv2.VideoCapture(str(video))
    for _ in range(6):
        _, expected = cap.read()
    cap.release()
    status, data = request(server, "GET", "/frame/cam1/5.jpg")
    assert status == 200 and data[:2] == b"\xff\xd8"
    got = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert got.shape == expected.shape
    error = np.abs(got.astype(float) - expected).mean()
    assert error < 8.0  # JPEG q90 of the same noisy frame
    # ...and clearly not a neighbouring frame (the blob moved).
    cap = cv2.VideoCapture(str(video))
    neighbour = [cap.read()[1] for _ in range(10)][-1]
    cap.release()
    assert np.abs(got.astype(float) - neighbour).max() > 100
    # Backwards (a seek) and the cache give the same frame.
    status, again = request(server, "GET", "/frame/cam1/5.jpg")
    status2, first = request(server, "GET", "/frame/cam1/0.jpg")
    assert again == data and status2 == 200 and first != data
    assert server.app.frames.hits >= 1


def test_frame_cache_is_bounded(workspace: Path, video: Path) -> None:
    options = LabelOptions(videos=[video], cache_mb=1)
    with LabelServer(workspace, options, track=fake_tracker) as running:
        running.app.frames.max_bytes = 100_000  # a few frames of ~28 kB
        for i in range(FRAMES):
            assert request(running, "GET", f"/frame/cam1/{i}.jpg")[0] == 200
        assert running.app.frames.cached_bytes <= 100_000
        assert 1 <= len(running.app.frames._cache) < FRAMES


def test_label_round_trip_and_hidden_and_delete(server: LabelServer, workspace: Path) -> None:
    changes = [
        {"video": "cam1", "frame": 3, "point": "head", "source": "label", "x": 100.25, "y": 50.5},
        {"video": "cam1", "frame": 3, "point": "tail", "source": "hidden"},
        {"video": "cam1", "frame": 7, "point": "head", "source": "label", "x": 10, "y": 20},
    ]
    status, answer = post(server, "/api/labels", {"changes": changes})
    assert status == 200 and answer["labels"] == 3
    with (workspace / "labels.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert rows == [
        {"video": "cam1", "frame": "3", "point": "head", "x": "100.250", "y": "50.500", "source": "label"},
        {"video": "cam1", "frame": "3", "point": "tail", "x": "", "y": "", "source": "hidden"},
        {"video": "cam1", "frame": "7", "point": "head", "x": "10.000", "y": "20.000", "source": "label"},
    ]
    status, data = request(server, "GET", "/api/labels?video=cam1")
    labels = json.loads(data)["labels"]
    assert {(r["frame"], r["point"], r["source"]) for r in labels} == {
        (3, "head", "label"),
        (3, "tail", "hidden"),
        (7, "head", "label"),
    }
    status, _ = post(
        server, "/api/labels", {"changes": [{"video": "cam1", "frame": 7, "point": "head", "source": "none"}]}
    )
    assert status == 200
    assert set(read_labels(workspace / "labels.csv")) == {("cam1", 3, "head"), ("cam1", 3, "tail")}


def test_labels_of_other_videos_and_outside_edits_are_kept(server: LabelServer, workspace: Path) -> None:
    path = workspace / "labels.csv"
    post(
        server,
        "/api/labels",
        {"changes": [{"video": "cam1", "frame": 0, "point": "head", "source": "label", "x": 1, "y": 2}]},
    )
    # Someone else (an import, a text editor) adds a row for another video between two clicks.
    text = path.read_text() + "other,4,knee,5.000,6.000,label\n"
    os.utime(path, ns=(0, 0))  # the stat signature must change even on coarse-mtime file systems
    path.write_text(text)
    post(
        server,
        "/api/labels",
        {"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": 3, "y": 4}]},
    )
    assert set(read_labels(path)) == {("cam1", 0, "head"), ("cam1", 1, "head"), ("other", 4, "knee")}


def test_points_add_and_rename_update_labels_and_tracks(server: LabelServer, workspace: Path) -> None:
    status, answer = post(server, "/api/points", {"op": "add", "name": "fin"})
    assert status == 200 and answer["points"] == ["head", "tail", "fin"]
    post(
        server,
        "/api/labels",
        {"changes": [{"video": "cam1", "frame": 2, "point": "head", "source": "label", "x": 30, "y": 40}]},
    )
    fake_tracker(workspace, {"cam1": Path()})
    status, answer = post(server, "/api/points", {"op": "rename", "old": "head", "new": "nose"})
    assert status == 200
    assert answer["points"] == ["nose", "tail", "fin"] and answer["connections"] == [["nose", "tail"]]
    assert set(read_labels(workspace / "labels.csv")) == {("cam1", 2, "nose")}
    status, data = request(server, "GET", "/api/tracks?video=cam1")
    assert [(t["frame"], t["point"]) for t in json.loads(data)["tracks"]] == [(3, "nose")]
    config = json.loads((workspace / "labeling.json").read_text())
    assert config["points"] == ["nose", "tail", "fin"]
    status, answer = post(server, "/api/points", {"op": "rename", "old": "tail", "new": "nose"})
    assert status == 400 and "exists" in answer["error"]


def test_track_runs_in_background_and_tracks_are_served(server: LabelServer) -> None:
    post(
        server,
        "/api/labels",
        {"changes": [{"video": "cam1", "frame": 4, "point": "tail", "source": "label", "x": 60, "y": 70}]},
    )
    status, answer = post(server, "/api/track", {"videos": ["cam1"]})
    assert status == 202 and answer["videos"] == ["cam1"]
    final = server.app.track_job.wait(30)
    assert final.state.value == "done", final.message
    status, data = request(server, "GET", "/api/tracks?video=cam1")
    assert json.loads(data)["tracks"] == [{"frame": 5, "point": "tail", "x": 61.0, "y": 70.0, "score": 0.5}]
    status, data = request(server, "GET", "/api/track")
    after_run = json.loads(data)
    assert after_run["seq"] == 1 and after_run["frames"] == {"cam1": FRAMES}
    # A run from a shell (`dynrecon track`) changes the version the page watches.
    fake_tracker(server.app.workspace, {})
    status, data = request(server, "GET", "/api/track")
    assert json.loads(data)["tracks_version"] != after_run["tracks_version"]


def test_tracker_failure_is_reported_not_fatal(workspace: Path, video: Path) -> None:
    def broken(ws: Path, videos: dict[str, Path]) -> Path:
        raise RuntimeError("boom")

    with LabelServer(workspace, LabelOptions(videos=[video]), track=broken) as running:
        assert post(running, "/api/track", {"videos": None})[0] == 202
        status = running.app.track_job.wait(30)
        assert status.state.value == "failed" and "boom" in status.message
        assert request(running, "GET", "/api/state")[0] == 200


@pytest.mark.parametrize(
    "path",
    [
        "/static/../../../../etc/passwd",
        "/static/..%2f..%2f..%2fetc%2fpasswd",
        "/static/%2e%2e/server.py",
        "/static/../server.py",
        "/ws/../cam1.avi",
        "/ws/%2e%2e/cam1.avi",
        "/ws/..%2fcam1.avi",
        "/ws/%2fetc%2fpasswd",
        "/ws//etc/passwd",
        "/ws/" + LOCK_NAME,
        "/frame/..%2fcam1/0.jpg",
        "/frame/cam1/../../etc/passwd",
        "/frame/cam1/999.jpg",
        "/frame/cam1/-1.jpg",
        "/frame/nope/0.jpg",
        "/etc/passwd",
        "//etc/passwd",
        "/api/nothing",
    ],
)
def test_path_traversal_and_unknown_paths_are_404(server: LabelServer, workspace: Path, path: str) -> None:
    (workspace.parent / "secret.txt").write_text("secret")
    status, data = request(server, "GET", path)
    assert status == 404, path
    assert b"secret" not in data and b"root:" not in data


def test_symlink_out_of_the_workspace_is_404(server: LabelServer, workspace: Path) -> None:
    (workspace.parent / "secret.txt").write_text("secret")
    (workspace / "link.txt").symlink_to(workspace.parent / "secret.txt")
    assert request(server, "GET", "/ws/link.txt")[0] == 404


def test_workspace_files_are_served(server: LabelServer) -> None:
    post(
        server,
        "/api/labels",
        {"changes": [{"video": "cam1", "frame": 0, "point": "head", "source": "label", "x": 1, "y": 2}]},
    )
    status, data = request(server, "GET", "/ws/labels.csv")
    assert status == 200 and data.startswith(b"video,frame,point,x,y,source\n")


@pytest.mark.parametrize(
    "body",
    [
        "not json",
        "[1, 2]",
        "{}",
        '{"changes": 5}',
        '{"changes": [5]}',
        '{"changes": [{"video": "cam1", "frame": "3", "point": "head", "source": "label", "x": 1, "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": true, "point": "head", "source": "label", "x": 1, "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": 99, "point": "head", "source": "label", "x": 1, "y": 1}]}',
        '{"changes": [{"video": "nope", "frame": 1, "point": "head", "source": "label", "x": 1, "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": 1, "point": "nope", "source": "label", "x": 1, "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": "a", "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": NaN, "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": 1e9, "y": 1}]}',
        '{"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "magic"}]}',
        '{"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": 1, "y": 1}, 7]}',
        b"\xff\xfe\x00garbage",
    ],
)
def test_malformed_label_posts_are_400_and_change_nothing(
    server: LabelServer, workspace: Path, body: str | bytes
) -> None:
    status, data = request(server, "POST", "/api/labels", body)
    assert status == 400, data
    assert "error" in json.loads(data)
    assert not (workspace / "labels.csv").exists()
    assert request(server, "GET", "/api/state")[0] == 200  # still serving


@pytest.mark.parametrize(
    ("path", "body"),
    [
        ("/api/points", '{"op": "explode"}'),
        ("/api/points", '{"op": "add", "name": "a,b"}'),
        ("/api/points", '{"op": "add", "name": ""}'),
        ("/api/points", '{"op": "rename", "old": "nope", "new": "x"}'),
        ("/api/track", '{"videos": ["nope"]}'),
        ("/api/track", '{"videos": 3}'),
    ],
)
def test_malformed_point_and_track_posts_are_400(server: LabelServer, path: str, body: str) -> None:
    assert request(server, "POST", path, body)[0] == 400


def test_malformed_queries_and_headers_are_400(server: LabelServer) -> None:
    assert request(server, "GET", "/api/labels")[0] == 400
    assert request(server, "GET", "/api/labels?video=nope")[0] == 400
    assert request(server, "GET", "/api/tracks?video=cam1&video=cam1")[0] == 400
    host, port = server.httpd.server_address[:2]
    conn = http.client.HTTPConnection(str(host), int(port), timeout=10)
    conn.putrequest("POST", "/api/labels")
    conn.putheader("Content-Length", "abc")
    conn.endheaders()
    assert conn.getresponse().status == 400
    conn.close()
    assert request(server, "POST", "/api/labels", "x" * 10, {"Content-Length": str(10 << 20)})[0] == 400


def test_foreign_host_header_is_refused(server: LabelServer) -> None:
    status, _ = request(server, "GET", "/api/state", headers={"Host": "evil.example:80"})
    assert status == 403


def test_cross_site_posts_change_nothing(server: LabelServer, workspace: Path) -> None:
    body = json.dumps({"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": 1, "y": 1}]})
    # What a form or a no-cors fetch on another site can send: text/plain, and an Origin header.
    assert request(server, "POST", "/api/labels", body, {"Content-Type": "text/plain"})[0] == 400
    assert request(server, "POST", "/api/labels", body, {"Origin": "http://evil.example"})[0] == 403
    assert not (workspace / "labels.csv").exists()
    port = server.httpd.server_address[1]
    assert request(server, "POST", "/api/labels", body, {"Origin": f"http://127.0.0.1:{port}"})[0] == 200


def test_second_server_on_the_same_workspace_is_refused(server: LabelServer, workspace: Path, video: Path) -> None:
    with pytest.raises(WorkspaceLockedError, match="another labeling server"):
        LabelServer(workspace, LabelOptions(videos=[video]), track=fake_tracker)
    assert request(server, "GET", "/api/state")[0] == 200  # the first one is unaffected


def test_stale_lock_of_a_dead_process_is_taken_over(workspace: Path, video: Path) -> None:
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True
    )
    import socket

    (workspace / LOCK_NAME).write_text(
        json.dumps({"pid": int(dead.stdout), "host": socket.gethostname(), "url": "http://127.0.0.1:1/"})
    )
    with LabelServer(workspace, LabelOptions(videos=[video]), track=fake_tracker) as running:
        assert json.loads((workspace / LOCK_NAME).read_text())["pid"] == os.getpid()
        assert request(running, "GET", "/api/state")[0] == 200
    assert not (workspace / LOCK_NAME).exists()  # released on stop
