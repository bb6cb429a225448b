"""`dynrecon label WS`: open a workspace for labeling and serve the page until interrupted."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from http.server import ThreadingHTTPServer
from pathlib import Path

from dynrecon.atomic import remove_temp_files
from dynrecon.errors import InputError
from dynrecon.lock import WorkspaceLock
from labeling.frames import probe_video
from labeling.server import LabelingApp, make_server
from labeling.skeleton import Skeleton
from labeling.tracker import TrackFunction, track_with_tracking_stage
from labeling.workspace import load_config, resolve_videos, save_config
from tracking.workspace import CONFIG_NAME

log = logging.getLogger(__name__)

JPEG_QUALITY = 90  # of the frames sent to the page


@dataclass(kw_only=True)
class LabelOptions:
    videos: list[Path] = field(default_factory=list)  # empty: remembered in labeling.json, else WS/videos/*
    skeleton: Skeleton = field(default_factory=Skeleton)  # --points / --skeleton, merged into labeling.json
    host: str = "127.0.0.1"
    port: int = 0  # 0: any free port
    cache_mb: int = 256  # bound of the JPEG frame cache


class LabelServer:
    """A running server (in a background thread); `stop()` shuts it down and releases the workspace lock."""

    def __init__(self, workspace: Path, options: LabelOptions, track: TrackFunction = track_with_tracking_stage):
        if workspace.exists() and not workspace.is_dir():
            raise InputError(workspace, "workspace is not a directory", fix="give a folder (made if missing)")
        workspace.mkdir(parents=True, exist_ok=True)
        self.lock = WorkspaceLock(workspace)
        self.lock.acquire()
        # A server killed mid-write leaves its temporary file; the lock now keeps every other server off.
        remove_temp_files(workspace / CONFIG_NAME)
        app: LabelingApp | None = None
        httpd: ThreadingHTTPServer | None = None
        try:
            config = load_config(workspace)
            videos = resolve_videos(workspace, options.videos, config.videos)
            config.videos = videos
            config.skeleton.merge(options.skeleton)
            infos = {name: probe_video(name, path) for name, path in videos.items()}
            save_config(workspace, config)
            app = LabelingApp(
                workspace, config, infos, track=track, cache_bytes=options.cache_mb << 20, jpeg_quality=JPEG_QUALITY
            )
            # Points already labeled (e.g. by hand in labels.csv) appear in the list even if not configured.
            for _, _, point in app.labels.snapshot():
                config.skeleton.add_point(point)
            httpd = make_server(app, options.host, options.port)
            host = options.host if ":" not in options.host else f"[{options.host}]"
            self.url = f"http://{host}:{httpd.server_address[1]}/"
            self.lock.update_url(self.url)
        except BaseException:
            # Stop the frame scan before the error reaches the interpreter's exit: a thread still inside
            # OpenCV then aborts the process (exit 134) instead of the one-line error.
            if httpd is not None:
                httpd.server_close()
            if app is not None:
                app.close()
            self.lock.release()
            raise
        self.app, self.httpd = app, httpd
        if options.host not in ("127.0.0.1", "localhost", "::1"):
            log.warning("serving on %s: anyone who can reach this address can read and change the labels", options.host)
        self._thread: threading.Thread | None = None
        self.stopped = False

    def start(self) -> LabelServer:
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="label-server", daemon=True)
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        try:
            self.httpd.serve_forever()
        finally:
            self.stop()

    def stop(self) -> None:
        if self.stopped:  # `run` stops it on every way out, `serve_forever` too
            return
        self.stopped = True
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join()
            self._thread = None
        self.httpd.server_close()
        self.app.close()
        self.lock.release()

    def __enter__(self) -> LabelServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def run(workspace: Path, options: LabelOptions, on_ready: Callable[[str], None] | None = None) -> Path:
    """Serve until Ctrl+C; `on_ready(url)` is called once the port is bound. Returns the labels file."""
    if threading.current_thread() is threading.main_thread():
        # `kill` (SIGTERM) stops like Ctrl+C: the lock file is removed and the port released. Set before the server
        # starts: a stop that came between its start and the loop left its threads running (the process hung).
        signal.signal(signal.SIGTERM, _interrupt)
    server = LabelServer(workspace, options)
    try:
        log.info("serving %s at %s", workspace, server.url)
        if on_ready is not None:
            on_ready(server.url)
        server.serve_forever()
    except KeyboardInterrupt:
        log.info("stopped")
    finally:
        server.stop()
    return workspace / "labels.csv"
