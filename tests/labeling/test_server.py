"""HTTP tests of the labeling server on an ephemeral port: label round trip, safety (404/400), lock file."""

from __future__ import annotations

import contextlib
import csv
import errno
import http.client
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from labeling_videos import FRAMES, HEIGHT, WIDTH

from dynrecon import atomic
from dynrecon.lock import LOCK_NAME, OUTPUT_LOCK_NAME, WorkspaceLockedError
from labeling.server import READ_TIMEOUT, Handler
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
        "/ws/" + OUTPUT_LOCK_NAME,
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
    (workspace / OUTPUT_LOCK_NAME).write_text('{"pid": 1, "host": "secret"}')  # a `dynrecon run` into the workspace
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
    assert request(server, "POST", "/api/labels", "x" * 10, {"Content-Length": str(10 << 20)})[0] == 413


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
    (workspace / LOCK_NAME).write_text(
        json.dumps({"pid": int(dead.stdout), "host": socket.gethostname(), "url": "http://127.0.0.1:1/"})
    )
    with LabelServer(workspace, LabelOptions(videos=[video]), track=fake_tracker) as running:
        assert json.loads((workspace / LOCK_NAME).read_text())["pid"] == os.getpid()
        assert request(running, "GET", "/api/state")[0] == 200
    assert not (workspace / LOCK_NAME).exists()  # released on stop


def raw_request(server: LabelServer, data: bytes, *, wait: float = 10.0) -> bytes:
    """Send bytes as they are (headers no HTTP client would write) and return the whole answer."""
    host, port = server.httpd.server_address[:2]
    with socket.create_connection((str(host), int(port)), timeout=wait) as sock:
        sock.sendall(data)
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


def status_of(answer: bytes) -> int:
    return int(answer.split(b" ", 2)[1])


def test_deeply_nested_json_is_400(server: LabelServer, workspace: Path) -> None:
    status, data = request(server, "POST", "/api/labels", "[" * 100_000)
    assert status == 400 and "nested too deeply" in json.loads(data)["error"]
    status, data = request(server, "POST", "/api/labels", '{"changes": [{"frame": ' + "9" * 5000 + "}]}")
    assert status == 400
    assert not (workspace / "labels.csv").exists()


@pytest.mark.parametrize("length", ["²", "٣", "-1", "1e3", "0x10", ""])
def test_non_ascii_or_signed_content_length_is_400(server: LabelServer, length: str) -> None:
    host = f"127.0.0.1:{server.httpd.server_address[1]}"
    head = f"POST /api/labels HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n"
    head += f"Content-Length: {length}\r\n\r\n"
    answer = raw_request(server, head.encode("utf-8") + b"{}")
    assert status_of(answer) == 400, answer


def test_frame_numbers_are_ascii_digits_only(server: LabelServer) -> None:
    assert request(server, "GET", "/frame/cam1/3.jpg")[0] == 200
    # "٣" (Arabic-Indic three) and "²" pass str.isdigit(); neither is frame 3 nor a crash.
    for name in ("%D9%A3", "%C2%B2", "%EF%BC%93", "9223372036854775808", "1" * 5000, "-1", "+3", "%203", "3%00"):
        status, data = request(server, "GET", f"/frame/cam1/{name}.jpg")
        assert status == 404, (name, data)
    assert request(server, "GET", "/frame/cam0/%C2%B2.jpg")[0] == 404


def test_unusable_workspace_names_are_404(server: LabelServer, workspace: Path) -> None:
    (workspace / "loop").symlink_to(workspace / "loop")
    for path in ("/ws/" + "x" * 5000, "/ws/loop", "/ws/loop/x", "/ws/%FF" * 300):
        assert request(server, "GET", path)[0] == 404, path[:20]


def test_malformed_urls_are_4xx(server: LabelServer) -> None:
    for path in (
        "//[x/api/state",
        "/api/labels?" + "&".join(f"v{i}=1" for i in range(200)),
        "/%ZZ",
        "/%7F",
        "/frame/cam1/%FF.jpg",
    ):
        status, _ = request(server, "GET", path)
        assert 400 <= status < 500, path


def test_oversized_body_is_413_and_read_no_further(server: LabelServer, workspace: Path) -> None:
    status, data = request(server, "POST", "/api/labels", "x" * 10, {"Content-Length": str(10 << 20)})
    assert status == 413 and "larger than" in json.loads(data)["error"]
    body = ("[" + "0," * (1 << 20) + "0]").encode()
    host_, port = server.httpd.server_address[:2]
    head = (
        f"POST /api/labels HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    )
    with socket.create_connection((str(host_), int(port)), timeout=10) as sock:
        # Headers only: the server answers from Content-Length and reads no further (bytes it leaves unread would
        # make its close a reset that can race the answer).
        sock.sendall(head.encode())
        answer = sock.recv(65536)
    assert status_of(answer) == 413
    assert not (workspace / "labels.csv").exists()
    assert request(server, "GET", "/api/state")[0] == 200


def test_short_body_is_400(server: LabelServer) -> None:
    host = f"127.0.0.1:{server.httpd.server_address[1]}"
    head = f"POST /api/labels HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\nContent-Length: 50\r\n\r\n"
    host_, port = server.httpd.server_address[:2]
    with socket.create_connection((str(host_), int(port)), timeout=10) as sock:
        sock.sendall(head.encode() + b'{"changes": []}')
        sock.shutdown(socket.SHUT_WR)  # the client hangs up its side: the body ends early
        answer = sock.recv(65536)
    assert status_of(answer) == 400


def test_a_body_that_never_arrives_frees_the_thread(server: LabelServer, monkeypatch: pytest.MonkeyPatch) -> None:
    assert Handler.timeout == READ_TIMEOUT == 10.0
    monkeypatch.setattr(server.httpd.RequestHandlerClass, "timeout", 0.5)
    host = f"127.0.0.1:{server.httpd.server_address[1]}"
    head = f"POST /api/labels HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n"
    start = time.monotonic()
    answer = raw_request(server, head.encode() + b'{"changes"')
    assert time.monotonic() - start < 5
    assert status_of(answer) == 408 and b"did not arrive" in answer


def test_a_body_trickled_byte_by_byte_is_cut_off(server: LabelServer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(server.httpd.RequestHandlerClass, "timeout", 0.5)
    host_, port = server.httpd.server_address[:2]
    head = f"POST /api/labels HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
    start = time.monotonic()
    with socket.create_connection((str(host_), int(port)), timeout=10) as sock:
        sock.sendall(head.encode() + b"Content-Length: 1000\r\n\r\n")
        answer = b""
        with contextlib.suppress(OSError):
            for _ in range(40):  # one byte every 0.1 s: each wait is short, the whole is too long
                sock.sendall(b" ")
                time.sleep(0.1)
            answer = sock.recv(65536)
        if not answer:
            answer = sock.recv(65536)
    assert time.monotonic() - start < 8
    assert answer == b"" or status_of(answer) == 408


def test_an_idle_connection_is_closed(server: LabelServer, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(server.httpd.RequestHandlerClass, "timeout", 0.5)
    host_, port = server.httpd.server_address[:2]
    with socket.create_connection((str(host_), int(port)), timeout=5) as sock:
        sock.sendall(b"GET /api/state HTTP/1.1\r\n")  # headers that never end
        start = time.monotonic()
        assert sock.recv(65536) == b""
    assert time.monotonic() - start < 4


LABEL_CLICK = {"changes": [{"video": "cam1", "frame": 1, "point": "head", "source": "label", "x": 3, "y": 4}]}


@pytest.mark.parametrize(
    ("code", "reason", "status"),
    [
        (errno.ENOSPC, "No space left on device", 507),
        (errno.EDQUOT, "Disk quota exceeded", 507),
        (errno.EROFS, "Read-only file system", 503),
        (errno.EACCES, "Permission denied", 503),
    ],
)
def test_a_failed_save_tells_the_page_why(
    server: LabelServer, workspace: Path, monkeypatch: pytest.MonkeyPatch, code: int, reason: str, status: int
) -> None:
    assert post(server, "/api/labels", LABEL_CLICK)[0] == 200
    before = (workspace / "labels.csv").read_bytes()

    def fail(*args: object, **kwargs: object) -> None:
        raise OSError(code, reason)

    monkeypatch.setattr(atomic.os, "fsync", fail)
    click = {"changes": [{"video": "cam1", "frame": 2, "point": "head", "source": "label", "x": 3, "y": 4}]}
    got, data = post(server, "/api/labels", click)
    assert got == status
    assert data["error"].startswith(f"cannot save labels.csv: {reason} (") and "\n" not in data["error"]
    got, data = post(server, "/api/points", {"op": "add", "name": "knee"})
    assert got == status and data["error"].startswith(f"cannot save labeling.json: {reason}")
    assert (workspace / "labels.csv").read_bytes() == before
    assert sorted(p.name for p in workspace.iterdir() if p.name.endswith(".tmp")) == []
    monkeypatch.undo()
    assert post(server, "/api/labels", click)[0] == 200  # the page's retry succeeds once there is room


def test_a_broken_labels_file_is_a_503_with_its_line(server: LabelServer, workspace: Path) -> None:
    (workspace / "labels.csv").write_text("video,frame,point,x,y,source\ncam1,zero,head,1,2,label\n")
    status, data = post(server, "/api/labels", LABEL_CLICK)
    assert status == 503 and "line 2" in data["error"]
    assert request(server, "GET", "/api/labels?video=cam1")[0] == 503


def test_a_burst_of_clicks_during_outside_edits_loses_no_click(server: LabelServer, workspace: Path) -> None:
    path = workspace / "labels.csv"
    stop = threading.Event()

    i_last = [-1]

    def outside_editor() -> None:
        i = 0
        while not stop.is_set():  # a text editor saving an old copy plus a row of its own
            stale = path.read_text() if path.exists() else "video,frame,point,x,y,source\n"
            time.sleep(0.02)
            path.write_text(stale + f"other,{i},knee,5.000,6.000,label\n")
            i_last[0] = i
            i += 1

    def clicker(point: str) -> None:
        for frame in range(FRAMES):
            change = {"video": "cam1", "frame": frame, "point": point, "source": "label", "x": frame, "y": 1}
            assert post(server, "/api/labels", {"changes": [change]})[0] == 200

    editor = threading.Thread(target=outside_editor)
    editor.start()
    clickers = [threading.Thread(target=clicker, args=(p,)) for p in ("head", "tail")]
    for thread in clickers:
        thread.start()
    for thread in clickers:
        thread.join()
    stop.set()
    editor.join()
    last_outside_row = ("other", i_last[0], "knee")
    data = request(server, "GET", "/api/labels?video=cam1")[1]
    served = {(r["frame"], r["point"]) for r in json.loads(data)["labels"]}
    clicks = {(f, p) for f in range(FRAMES) for p in ("head", "tail")}
    assert clicks <= served
    assert post(server, "/api/labels", LABEL_CLICK)[0] == 200
    on_disk = set(read_labels(path))
    assert {("cam1", f, p) for f, p in clicks} <= on_disk and last_outside_row in on_disk


def test_interrupted_writes_leave_no_temporary_file(workspace: Path, video: Path) -> None:
    (workspace / ".labels.csv.k1ll3d.tmp").write_text("video,frame,po")  # a server killed mid-write
    (workspace / ".labeling.json.k1ll3d.tmp").write_text('{"points": [')
    options = LabelOptions(videos=[video], skeleton=Skeleton(points=["head"]))
    with LabelServer(workspace, options, track=fake_tracker) as running:
        assert not list(workspace.glob(".label*.tmp"))
        assert post(running, "/api/labels", LABEL_CLICK)[0] == 200
    assert not list(workspace.glob("*.tmp")) and not list(workspace.glob(".*.tmp"))


@pytest.mark.parametrize("method", ["PUT", "DELETE", "PATCH", "OPTIONS", "FOO"])
def test_other_methods_are_405(server: LabelServer, method: str) -> None:
    host, port = server.httpd.server_address[:2]
    conn = http.client.HTTPConnection(str(host), int(port), timeout=10)
    try:
        conn.request(method, "/api/labels", body="{}", headers={"Content-Type": "application/json"})
        response = conn.getresponse()
        assert response.status == 405 and response.getheader("Allow") == "GET, HEAD, POST"
        assert "not allowed" in json.loads(response.read())["error"]
    finally:
        conn.close()
