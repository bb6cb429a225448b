"""The labeling web server: static page, frames as JPEG, labels/tracks as JSON (see labeling/static/app.js).

Routes (everything else is 404; bad input is 4xx, never a crash or a 500):
    GET  /                          the page
    GET  /static/NAME               page files (only files shipped in labeling/static)
    GET  /ws/NAME                   files inside the workspace (e.g. labels.csv), nothing outside it
    GET  /frame/VIDEO/N.jpg         frame N of a video, decoded on demand
    GET  /api/state                 videos, points, connections, tracking status
    GET  /api/labels?video=V        manual labels of a video
    GET  /api/tracks?video=V        tracked points (tracks.csv rows with source != label) of a video
    GET  /api/track                 tracking status
    POST /api/labels                {"changes": [{"video", "frame", "point", "source", "x", "y"}]}
                                    with source label (x, y given), hidden, or none (remove the label)
    POST /api/points                {"op": "add", "name"} or {"op": "rename", "old", "new"}
    POST /api/track                 {"videos": [names] or null for all}

Errors are one-line JSON {"error": "..."}: 400 malformed, 403 another site, 404, 405 other methods, 408 a body
that stalls (READ_TIMEOUT), 409 busy, 413 a body over MAX_BODY; 503 labels.csv unreadable or not writable, 507
a full disk (the page shows the line and retries).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import socket
import threading
import time
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

from dynrecon.errors import DynreconError, InputError
from dynrecon.lock import LOCK_NAME, OUTPUT_LOCK_NAME
from labeling.frames import FrameCache, VideoInfo
from labeling.labels import Change, LabelStore, SaveError, StoreClosedError
from labeling.skeleton import Skeleton, valid_point_name
from labeling.tracker import TrackFunction, TrackJob
from labeling.workspace import WorkspaceConfig, save_config
from tracking.labels import Label, Source

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
MAX_BODY = 1 << 20
# A client that promised a body (or headers) and stalls gives its thread back after this long.
READ_TIMEOUT = 10.0
ASCII_NUMBER = re.compile(r"[0-9]{1,12}")  # str.isdigit() also takes "²" and "٣" (Arabic-Indic 3)
FRAME_FILE = re.compile(r"([0-9]{1,12})\.jpg")
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".csv": "text/csv; charset=utf-8",
    ".json": "application/json",
    ".txt": "text/plain; charset=utf-8",
}


class BadRequestError(Exception):
    """Malformed request: answered with 400 and the message."""


class ForbiddenError(Exception):
    """A request from another web site: 403."""


class ConflictError(Exception):
    """Valid request that cannot run now (e.g. tracking already running): 409."""


class RequestError(Exception):
    """A request the server refuses with a given 4xx status (413 body too large, 408 body never came)."""

    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


@dataclass(kw_only=True)
class TrackRow:
    frame: int
    point: str
    x: float
    y: float
    score: float | None


class LabelingApp:
    """State shared by all request threads; `LabelStore` serializes label writes, `_config_lock` the rest."""

    def __init__(
        self,
        workspace: Path,
        config: WorkspaceConfig,
        videos: dict[str, VideoInfo],
        *,
        track: TrackFunction,
        cache_bytes: int = 256 << 20,
        jpeg_quality: int = 90,
    ):
        self.workspace = workspace.resolve()
        self.config = config
        self.videos = videos
        self.frames = FrameCache(videos, max_bytes=cache_bytes, jpeg_quality=jpeg_quality)
        try:
            self.labels = LabelStore(self.workspace / "labels.csv")
            self.track_job = TrackJob(self.workspace, track)
        except BaseException:
            # The frame scan must not be inside OpenCV when the interpreter exits (C++ terminate, SIGABRT).
            self.frames.close()
            raise
        self._config_lock = threading.Lock()
        self._tracks_lock = threading.Lock()
        self._tracks_cache: tuple[tuple[int, int] | None, dict[str, list[TrackRow]]] = (None, {})
        self.allowed_hosts: set[str] | None = None  # Host headers accepted; None = any (set by make_server)
        self.static_files = {p.name for p in STATIC_DIR.glob("*") if p.is_file()}

    @property
    def skeleton(self) -> Skeleton:
        return self.config.skeleton

    # ---- reads
    def state(self) -> dict[str, Any]:
        with self._config_lock:
            points = list(self.skeleton.points)
            connections = [list(c) for c in self.skeleton.connections]
        return {
            "workspace": str(self.workspace),
            "videos": [
                {
                    "name": v.name,
                    "frames": self.frames.frame_count(v.name),
                    "width": v.width,
                    "height": v.height,
                    "fps": v.fps,
                }
                for v in self.videos.values()
            ],
            "points": points,
            "connections": connections,
            "track": self.track_status(),
        }

    def track_status(self) -> dict[str, Any]:
        """Tracking job status, plus what lets the page notice outside changes: the version of tracks.csv
        (a `dynrecon track` run from a shell) and the exact frame counts once the frame scan has them."""
        status = self.track_job.status().as_json()
        try:
            st = os.stat(self.workspace / "tracks.csv")
            status["tracks_version"] = f"{st.st_mtime_ns}-{st.st_size}"
        except FileNotFoundError:
            status["tracks_version"] = ""
        status["frames"] = {name: self.frames.frame_count(name) for name in self.videos}
        return status

    def labels_of(self, video: str) -> list[dict[str, Any]]:
        rows = []
        for (_, frame, point), label in sorted(self.labels.snapshot(video).items()):
            row: dict[str, Any] = {"frame": frame, "point": point, "source": label.source.value}
            if label.xy is not None:
                row["x"], row["y"] = label.xy
            rows.append(row)
        return rows

    def tracks_of(self, video: str) -> list[dict[str, Any]]:
        return [
            {"frame": r.frame, "point": r.point, "x": r.x, "y": r.y, "score": r.score}
            for r in self._read_tracks().get(video, [])
        ]

    def _read_tracks(self) -> dict[str, list[TrackRow]]:
        """tracks.csv rows made by the tracker (labels come from labels.csv), cached until it changes."""
        from tracking.tracks import read_tracks

        path = self.workspace / "tracks.csv"
        with self._tracks_lock:
            try:
                st = os.stat(path)
                signature: tuple[int, int] | None = (st.st_mtime_ns, st.st_size)
            except FileNotFoundError:
                signature = None
            if signature == self._tracks_cache[0]:
                return self._tracks_cache[1]
            by_video: dict[str, list[TrackRow]] = {}
            if signature is not None:
                tracks = read_tracks(path)
                sources = tracks.extra.get("source", [""] * len(tracks))
                scores = tracks.extra.get("score", [""] * len(tracks))
                for i in range(len(tracks)):
                    if sources[i] == "label":
                        continue
                    try:
                        score: float | None = float(scores[i]) if scores[i] != "" else None
                    except ValueError:
                        score = None
                    if score is not None and not math.isfinite(score):
                        score = None
                    by_video.setdefault(tracks.video[i], []).append(
                        TrackRow(
                            frame=int(tracks.frame[i]),
                            point=tracks.point[i],
                            x=float(tracks.xy[i, 0]),
                            y=float(tracks.xy[i, 1]),
                            score=score,
                        )
                    )
            self._tracks_cache = (signature, by_video)
            return by_video

    # ---- writes
    def apply_changes(self, body: Any) -> dict[str, Any]:
        changes_raw = _field(body, "changes", list)
        if len(changes_raw) > 10000:
            raise BadRequestError("too many changes in one request (at most 10000)")
        changes = [self._parse_change(i, c) for i, c in enumerate(changes_raw)]
        with self._config_lock:
            order = list(self.skeleton.points)
        count = self.labels.apply(changes, order)
        return {"ok": True, "labels": count}

    def _parse_change(self, i: int, raw: Any) -> Change:
        if not isinstance(raw, dict):
            raise BadRequestError(f"change {i} is not an object")
        video = _field(raw, "video", str)
        info = self.videos.get(video)
        if info is None:
            raise BadRequestError(f"change {i}: unknown video {video!r}")
        frame = _field(raw, "frame", int)
        count = self.frames.frame_count(video)
        if not 0 <= frame < count:
            raise BadRequestError(f"change {i}: frame {frame} outside 0..{count - 1}")
        point = _field(raw, "point", str)
        with self._config_lock:
            if point not in self.skeleton.points:
                raise BadRequestError(f"change {i}: unknown point {point!r} (add it first)")
        source = _field(raw, "source", str)
        key = (video, frame, point)
        if source == "none":
            return Change(key=key, label=None)
        if source == Source.HIDDEN.value:
            return Change(key=key, label=Label(source=Source.HIDDEN))
        if source != Source.LABEL.value:
            raise BadRequestError(f"change {i}: source must be label, hidden or none, not {source!r}")
        x, y = _number(raw, "x"), _number(raw, "y")
        # Pixel centres run 0..W-1; the half pixel around them is still on the image.
        if not (-0.5 <= x <= info.width - 0.5 and -0.5 <= y <= info.height - 0.5):
            raise BadRequestError(f"change {i}: ({x}, {y}) is outside the {info.width}x{info.height} image")
        return Change(key=key, label=Label(source=Source.LABEL, xy=(x, y)))

    def edit_points(self, body: Any) -> dict[str, Any]:
        op = _field(body, "op", str)
        if op == "add":
            name = _point_name(body, "name")
            with self._config_lock:
                self.skeleton.add_point(name)
                self._save_config()
        elif op == "rename":
            old, new = _point_name(body, "old"), _point_name(body, "new")
            if self.track_job.running():
                raise ConflictError("cannot rename while tracking runs; try again when it has finished")
            with self._config_lock:
                if old not in self.skeleton.points:
                    raise BadRequestError(f"unknown point {old!r}")
                if new in self.skeleton.points:
                    raise BadRequestError(f"point {new!r} already exists")
                try:
                    self.labels.rename_point(old, new, self.skeleton.points)
                except ValueError as error:
                    raise BadRequestError(str(error)) from None
                self._rename_in_tracks(old, new)
                self.skeleton.rename(old, new)
                self._save_config()
        else:
            raise BadRequestError(f"op must be add or rename, not {op!r}")
        state = self.state()
        return {"points": state["points"], "connections": state["connections"]}

    def _save_config(self) -> None:
        try:
            save_config(self.workspace, self.config)
        except OSError as error:
            raise SaveError(self.workspace / "labeling.json", error) from None

    def _rename_in_tracks(self, old: str, new: str) -> None:
        from tracking.tracks import read_tracks, write_tracks

        path = self.workspace / "tracks.csv"
        with self._tracks_lock:
            if not path.exists():
                return
            tracks = read_tracks(path)
            if old in tracks.point:
                tracks.point = [new if p == old else p for p in tracks.point]
                try:
                    write_tracks(path, tracks)
                except OSError as error:
                    raise SaveError(path, error) from None

    def start_tracking(self, body: Any) -> dict[str, Any]:
        names = body.get("videos") if isinstance(body, dict) else None
        if names is None:
            names = list(self.videos)
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise BadRequestError("'videos' must be a non-empty list of video names or null")
        unknown = [n for n in names if n not in self.videos]
        if unknown:
            raise BadRequestError(f"unknown video {unknown[0]!r}")
        if not self.track_job.start({n: self.videos[n].path for n in names}):
            raise ConflictError("tracking is already running")
        return self.track_status()

    def close(self) -> None:
        self.labels.close()
        self.frames.close()


def _field(body: Any, name: str, kind: type) -> Any:
    if not isinstance(body, dict):
        raise BadRequestError("request body must be a JSON object")
    if name not in body:
        raise BadRequestError(f"missing field {name!r}")
    value = body[name]
    # bool is an int in Python; a frame of `true` is still malformed.
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise BadRequestError(f"field {name!r} must be of type {kind.__name__}")
    return value


def _number(body: dict, name: str) -> float:
    value = body.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise BadRequestError(f"field {name!r} must be a finite number")
    return float(value)


def _point_name(body: Any, name: str) -> str:
    value = _field(body, name, str)
    if not valid_point_name(value):
        raise BadRequestError(f"invalid point name {value!r}: up to 64 printable characters, none of , \" ' \\ / < >")
    return value


class Handler(BaseHTTPRequestHandler):
    server_version = "dynrecon-label"
    app: LabelingApp  # set on the subclass made by `make_server`
    timeout = READ_TIMEOUT  # socket timeout (StreamRequestHandler.setup): a stalled client frees its thread

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s %s", self.address_string(), format % args)

    # ---- dispatch
    def do_GET(self) -> None:
        self._dispatch(self._get)

    def do_HEAD(self) -> None:
        self._dispatch(self._get)

    def do_POST(self) -> None:
        self._dispatch(self._post)

    def __getattr__(self, name: str) -> Any:
        # Any other method (PUT, DELETE, FOO) is the client's mistake, 405, not the 501 of http.server.
        if name.startswith("do_"):
            return self._method_not_allowed
        raise AttributeError(name)

    def _method_not_allowed(self) -> None:
        self._error(HTTPStatus.METHOD_NOT_ALLOWED, f"method {self.command} is not allowed (GET, HEAD, POST)")

    def _dispatch(self, route: Any) -> None:
        try:
            allowed = self.app.allowed_hosts
            if allowed is not None and self.headers.get("Host", "") not in allowed:
                # A page on another site that rebinds its DNS name to 127.0.0.1 must not reach the labels.
                self._json({"error": "unexpected Host header"}, HTTPStatus.FORBIDDEN)
                return
            try:
                url = urlsplit(self.path)
                query = parse_qs(url.query, max_num_fields=100)
            except ValueError as error:  # "//[x" (a bad IPv6 host), too many query fields
                raise BadRequestError(f"malformed URL: {error}") from None
            # Decode each segment once; an encoded "/" or ".." inside a segment never becomes a path step.
            segments = [unquote(s) for s in url.path.split("/")[1:]]
            route(segments, query)
        except BadRequestError as error:
            self._error(HTTPStatus.BAD_REQUEST, str(error))
        except RequestError as error:
            self._error(error.status, str(error))
        except ConflictError as error:
            self._error(HTTPStatus.CONFLICT, str(error))
        except ForbiddenError as error:
            self._error(HTTPStatus.FORBIDDEN, str(error))
        except SaveError as error:  # a full disk, a read-only folder: the page shows this line and retries
            log.error("%s", error)
            status = HTTPStatus.INSUFFICIENT_STORAGE if error.disk_full else HTTPStatus.SERVICE_UNAVAILABLE
            self._error(status, str(error))
        except StoreClosedError as error:
            self._error(HTTPStatus.SERVICE_UNAVAILABLE, str(error))
        except DynreconError as error:  # a broken file in the workspace: tell the page which and why, it retries
            self._error(HTTPStatus.SERVICE_UNAVAILABLE, str(error))
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True
        except TimeoutError:  # the client stopped sending: answer if it still listens, then hang up
            self._error(HTTPStatus.REQUEST_TIMEOUT, f"the request body did not arrive within {self.timeout:g} s")
        except Exception:
            log.exception("internal error on %s %s", self.command, self.path)
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, "internal error (see the server log)")

    def _error(self, status: HTTPStatus, message: str) -> None:
        """A one-line JSON error; the connection is closed after it, as a body may be left unread."""
        self.close_connection = True
        extra = {"Allow": "GET, HEAD, POST"} if status == HTTPStatus.METHOD_NOT_ALLOWED else {}
        # The client may be gone (or stall on reading): then there is nobody left to tell.
        with contextlib.suppress(OSError):
            self._json({"error": message}, status, headers=extra)

    def _get(self, seg: list[str], query: dict[str, list[str]]) -> None:
        app = self.app
        if seg in ([""], ["index.html"]):
            return self._file(STATIC_DIR / "index.html")
        if len(seg) == 2 and seg[0] == "static" and seg[1] in app.static_files:
            return self._file(STATIC_DIR / seg[1])
        if len(seg) >= 2 and seg[0] == "ws":
            return self._workspace_file(seg[1:])
        frame_file = FRAME_FILE.fullmatch(seg[2]) if len(seg) == 3 and seg[0] == "frame" else None
        if frame_file is not None:
            data = app.frames.jpeg(seg[1], int(frame_file.group(1)))
            if data is None:
                return self._not_found()
            return self._bytes(data, "image/jpeg", cache=True)
        if seg == ["api", "state"]:
            return self._json(app.state())
        if seg == ["api", "labels"]:
            video = self._video_param(query)
            return self._json({"video": video, "labels": app.labels_of(video)})
        if seg == ["api", "tracks"]:
            video = self._video_param(query)
            return self._json({"video": video, "tracks": app.tracks_of(video)})
        if seg == ["api", "track"]:
            return self._json(app.track_status())
        return self._not_found()

    def _post(self, seg: list[str], query: dict[str, list[str]]) -> None:
        body = self._read_json()
        if seg == ["api", "labels"]:
            return self._json(self.app.apply_changes(body))
        if seg == ["api", "points"]:
            return self._json(self.app.edit_points(body))
        if seg == ["api", "track"]:
            return self._json(self.app.start_tracking(body), HTTPStatus.ACCEPTED)
        return self._not_found()

    # ---- helpers
    def _video_param(self, query: dict[str, list[str]]) -> str:
        values = query.get("video", [])
        if len(values) != 1 or values[0] not in self.app.videos:
            raise BadRequestError("query must name one known video: ?video=NAME")
        return values[0]

    def _read_json(self) -> Any:
        # A JSON content type makes a cross-site POST a "non-simple" request that browsers do not send
        # without a CORS preflight (which this server never grants); text/plain forms would get through.
        content_type = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
        if content_type != "application/json":
            raise BadRequestError("Content-Type must be application/json")
        origin = self.headers.get("Origin")
        allowed = self.app.allowed_hosts
        if origin is not None and allowed is not None and origin not in {f"http://{h}" for h in allowed}:
            raise ForbiddenError(f"requests from {origin} are not allowed")
        length_text = self.headers.get("Content-Length")
        if length_text is None or not ASCII_NUMBER.fullmatch(length_text.strip()):
            raise BadRequestError("Content-Length header missing or invalid")
        length = int(length_text)
        if length > MAX_BODY:
            raise RequestError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"body larger than {MAX_BODY} bytes")
        raw = self._read_body(length)
        if len(raw) < length:
            raise BadRequestError(f"body ended after {len(raw)} of {length} bytes")
        try:
            return json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as error:
            raise BadRequestError(f"body is not JSON: {error}") from None
        except RecursionError:
            raise BadRequestError("body is not JSON: nested too deeply") from None

    def _read_body(self, length: int) -> bytes:
        """Up to `length` bytes; the socket timeout bounds each wait, the deadline a body trickled byte by byte."""
        deadline = time.monotonic() + (self.timeout or READ_TIMEOUT)
        chunks: list[bytes] = []
        got = 0
        while got < length:
            if time.monotonic() > deadline:
                raise TimeoutError
            chunk = self.rfile.read1(min(1 << 16, length - got))
            if not chunk:
                break
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    def _workspace_file(self, parts: list[str]) -> None:
        root = self.app.workspace
        bad = any(p in ("", ".", "..") or "/" in p or "\\" in p or "\0" in p for p in parts)
        if bad or parts[-1] in (LOCK_NAME, OUTPUT_LOCK_NAME):  # a pid and a host name: not the page's
            return self._not_found()
        try:
            target = root.joinpath(*parts).resolve()
            # resolve() follows symlinks: a link pointing out of the workspace is refused like "..".
            found = target.is_relative_to(root) and target.is_file()
        except (OSError, RuntimeError):  # a name too long, a symlink loop
            found = False
        if not found:
            return self._not_found()
        return self._file(target)

    def _file(self, path: Path) -> None:
        try:
            data = path.read_bytes()
        except OSError:
            return self._not_found()
        self._bytes(data, CONTENT_TYPES.get(path.suffix.lower(), "application/octet-stream"))

    def _not_found(self) -> None:
        self._json({"error": "not found"}, HTTPStatus.NOT_FOUND)

    def _json(self, obj: Any, status: HTTPStatus = HTTPStatus.OK, *, headers: dict[str, str] | None = None) -> None:
        self._bytes(json.dumps(obj).encode("utf-8"), "application/json", status=status, headers=headers)

    def _bytes(
        self,
        data: bytes,
        content_type: str,
        *,
        status: HTTPStatus = HTTPStatus.OK,
        cache: bool = False,
        headers: dict[str, str] | None = None,
    ) -> None:
        self.send_response(status)
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "private, max-age=3600" if cache else "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(data)


class _Server6(ThreadingHTTPServer):
    address_family = socket.AF_INET6


def make_server(app: LabelingApp, host: str, port: int) -> ThreadingHTTPServer:
    """Bind (port 0 = any free port); serve with `serve_forever()`."""
    handler = type("BoundHandler", (Handler,), {"app": app})
    try:
        server = _Server6((host, port), handler) if ":" in host else ThreadingHTTPServer((host, port), handler)
    except OSError as error:  # port in use, address not on this machine, unknown host name
        reason = error.strerror or str(error)
        raise InputError(
            None,
            f"cannot listen on {host}:{port}: {reason}",
            fix="choose another --port (0: any free port) or an address of this machine for --host",
        ) from None
    server.daemon_threads = True
    bound_port = server.server_address[1]
    if host in ("127.0.0.1", "localhost", "::1"):
        app.allowed_hosts = {f"{name}:{bound_port}" for name in ("127.0.0.1", "localhost", "[::1]")}
    return server
