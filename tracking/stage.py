"""`dynrecon track WS`: propagate `WS/labels.csv` through every frame of the workspace's videos into
`tracks.csv`."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dynrecon.atomic import require_writable
from dynrecon.errors import InputError
from dynrecon.readers import shown
from tracking import labels as labels_csv
from tracking.frames import VideoFrames
from tracking.options import TrackOptions
from tracking.propagate import TrackedPoint, track_video
from tracking.tracks import IMAGE_MARGIN, SOURCE_LABEL, Tracks, inside_image, read_tracks, write_tracks
from tracking.workspace import LABELS_NAME, TRACKS_NAME, AllLabels, workspace_videos

log = logging.getLogger(__name__)


def run(
    workspace: str | Path,
    out: str | Path | None = None,
    options: TrackOptions | None = None,
    *,
    videos: dict[str, Path] | list[Path] | None = None,
) -> Path:
    """Track the labeled points of `videos` (default: all of the workspace's) and write `out` (default
    `WS/tracks.csv`). Rows of other videos already in `out` are kept, except where the labels now say
    otherwise. Returns the path written."""
    workspace = Path(workspace)
    options = options or TrackOptions()
    out = Path(out) if out is not None else workspace / TRACKS_NAME
    if out.is_dir():
        raise InputError(out, "is a folder", fix="--out names the tracks.csv file to write")
    require_writable(out.parent)  # before tracking every video, not after
    if isinstance(videos, dict):
        chosen = {name: Path(p) for name, p in videos.items()}
    else:
        chosen = workspace_videos(workspace, [Path(p) for p in videos] if videos else None)
    old = _existing(out)  # before any tracking: a file that is no tracks.csv fails at once
    labels_path = workspace / LABELS_NAME
    raw_labels = labels_csv.read_labels(labels_path)
    labels = _grouped(raw_labels)
    unknown = sorted(set(labels) - set(chosen)) if videos is None else []
    if unknown:
        log.warning("labels.csv names video(s) %s that the workspace does not list; not tracked", ", ".join(unknown))
    if not set(labels) & set(chosen):  # refused: writing would replace out's rows with none
        found = labels_path.exists() or labels_path.is_symlink()
        raise InputError(
            labels_path,
            ("has no labels for " if found else "not found: no labels for ")
            + ", ".join(chosen)
            + (f" (it labels {', '.join(sorted(labels))})" if labels else "")
            + f"; nothing to track, {out} left as it was",
            fix="video names must match the file names; label points with `dynrecon label WS`"
            if labels
            else "label points with `dynrecon label WS`, or import tracks with `dynrecon import-tracks`",
        )
    results: dict[str, dict[str, dict[int, TrackedPoint]]] = {}
    for name, path in chosen.items():
        marks = labels.get(name, {})
        if not any(xy is not None for frames in marks.values() for xy in frames.values()):
            log.info("%s: no labels; nothing to track", name)
            results[name] = {}
            continue
        frames = VideoFrames(path)
        try:
            _check_inside(raw_labels, labels_path, name, frames.shape)
            with tqdm(total=2 * len(frames), desc=f"track {name}", unit="frame", leave=False) as bar:
                results[name] = track_video(
                    frames, marks, options, progress=lambda done, total: bar.update(done - bar.n), name=name
                )
        finally:
            frames.close()
        tracked = sum(1 for pts in results[name].values() for p in pts.values() if p.source != SOURCE_LABEL)
        log.info("%s: %d labels, %d tracked positions", name, sum(len(v) for v in marks.values()), tracked)
        _say_lost(name, results[name], marks, len(frames))
    rows = _rows(results)
    rows += _kept_rows(old, set(results), labels)
    return write_tracks(out, _to_tracks(rows))


# A labeled point found on fewer than this share of its video's frames is named in a warning (the page's timeline
# shows where; the log alone gave totals over all points)
LOST_SHARE = 0.5


def _say_lost(name: str, tracked: dict[str, dict[int, TrackedPoint]], marks: dict, num_frames: int) -> None:
    """One warning for the points of video `name` found (labels and frames marked hidden included) on under
    LOST_SHARE of its frames, each with its frames found and its longest stretch without a position."""
    lost = []
    for point in sorted(marks):
        if not any(xy is not None for xy in marks[point].values()):
            continue  # marked hidden only: nothing was asked of the tracker
        # frames marked hidden are accounted for: the tracker was asked nothing there
        frames = sorted(set(tracked.get(point, {})) | {f for f, xy in marks[point].items() if xy is None})
        if len(frames) >= LOST_SHARE * num_frames:
            continue
        edges = [-1, *frames, num_frames]
        gap, at = max((b - a - 1, a + 1) for a, b in itertools.pairwise(edges))
        lost.append(f"{point!r} on {len(frames)} of {num_frames} frames (none in {at}-{at + gap - 1})")
    if lost:
        log.warning(
            "%s: tracked %s: lost by the tracker (too little texture, hidden, or fast): label it on more frames "
            "(`dynrecon label`)",
            name,
            "; ".join(lost),
        )


def _grouped(raw: dict[labels_csv.Key, labels_csv.Label]) -> AllLabels:
    """video -> point -> frame -> (x, y), or None for `source=hidden`."""
    labels: AllLabels = {}
    for (video, frame, point), label in raw.items():
        labels.setdefault(video, {}).setdefault(point, {})[frame] = label.xy
    return labels


def _check_inside(raw: dict[labels_csv.Key, labels_csv.Label], path: Path, video: str, shape: tuple[int, int]) -> None:
    """Refuse a label of `video` outside its image: it would go into tracks.csv with score 1 and spoil the solve."""
    height, width = shape
    for (name, frame, point), label in raw.items():
        if name != video or label.xy is None or inside_image(np.array(label.xy), width, height)[0]:
            continue
        raise InputError(
            path,
            f"label of point {shown(point)} in video {shown(video)} frame {frame} at x, y = "
            f"{label.xy[0]:.6g}, {label.xy[1]:.6g} is outside the {width}x{height} image",
            where=f"line {label.line}" if label.line is not None else None,
            fix=f"labels lie inside the image (within {round(100 * IMAGE_MARGIN)} % of its size): fix or delete it",
        )


Row = tuple[str, int, str, float, float, str, str]  # video, frame, point, x, y, source, score


def _rows(results: dict[str, dict[str, dict[int, TrackedPoint]]]) -> list[Row]:
    return [
        (video, frame, point, p.x, p.y, p.source, f"{p.score:.3f}")
        for video, points in results.items()
        for point, by_frame in points.items()
        for frame, p in by_frame.items()
    ]


def _existing(out: Path) -> Tracks:
    """The tracks already in `out` (none when it does not exist), whose rows of videos not tracked now are kept."""
    if not out.is_file():
        return Tracks()
    try:
        return read_tracks(out)
    except InputError as error:
        raise InputError(
            error.path,
            error.what,
            where=error.where,
            fix="it is the existing tracks file this run adds its videos to: give another --out, or remove it",
        ) from None


def _kept_rows(old: Tracks, replaced: set[str], labels: AllLabels) -> list[Row]:
    """Rows of videos not tracked this time: the current labels, plus `old` tracked rows the labels don't
    override."""
    rows: list[Row] = []
    others = set(labels) - replaced
    sources = old.extra.get("source", [""] * len(old))
    scores = old.extra.get("score", [""] * len(old))
    for i in range(len(old)):
        video, frame, point = old.video[i], int(old.frame[i]), old.point[i]
        if video in replaced or sources[i] == SOURCE_LABEL or frame in labels.get(video, {}).get(point, {}):
            continue
        others.add(video)
        rows.append((video, frame, point, float(old.xy[i, 0]), float(old.xy[i, 1]), sources[i], scores[i]))
    for video in others:
        for point, by_frame in labels.get(video, {}).items():
            for frame, xy in by_frame.items():
                if xy is not None:
                    rows.append((video, frame, point, xy[0], xy[1], SOURCE_LABEL, "1.000"))
    return rows


def _to_tracks(rows: list[Row]) -> Tracks:
    return Tracks.from_rows([r[:5] for r in rows], source=[r[5] for r in rows], score=[r[6] for r in rows])
