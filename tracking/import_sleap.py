"""SLEAP's files: its project / predictions files (.slp, `read_sleap_slp`) and its analysis HDF5
(`sleap-convert --format analysis`, or File > Export Analysis HDF5; sleap-io's `save_analysis_h5`): dense arrays of
every track's nodes over the video's frames (`read_sleap_analysis`).

Datasets: `tracks` (x, y; NaN = missing), `node_names`, `track_names`, optionally `point_scores`. Axis order: the
`dims` attribute of `tracks` where sleap-io wrote one (its `matlab` and `standard` presets), else SLEAP's own layout
(`transpose` true or absent: track, xy, node, frame; false: frame, node, xy, track). The frame axis starts at the
video's frame 0 (SLEAP's default `all_frames`; an export without it starts at the first labelled frame and does
not say which, so its frames would be shifted). SLEAP's tracks, like DeepLabCut's individuals, hold within a video:
`person` / `every_person` as in `tracking.people.individual_names`.

.slp (SLEAP formats 1.1 to below 3.0, as SLEAP and sleap-io write them: HDF5 tables `frames`, `instances`, `points`,
`pred_points`, JSON `metadata`, `tracks_json`, `videos_json`): every video of the file is imported under its file's
stem; per frame and track the user's instance where there is one (SLEAP hides that track's predictions), else the
prediction; points not visible are missing; untracked instances of a tracked file are left out (with a warning).
Older, newer, cropped or unknown layouts are refused with the export command.
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path, PurePath, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np

from dynrecon.errors import InputError
from tracking.detections import Detection
from tracking.people import individual_names

MATLAB = ("track", "xy", "node", "frame")  # SLEAP's analysis export
LEGACY_UNTRANSPOSED = ("frame", "node", "xy", "track")
CANONICAL = ("frame", "track", "node", "xy")
log = logging.getLogger(__name__)
_EXPORT_NAME = re.compile(r".+\.\d{3}_(.+)")  # SLEAP's default export name <labels>.<index>_<video>
EXPORT_FIX = "export SLEAP's analysis HDF5: sleap-convert --format analysis FILE.slp (or File > Export Analysis HDF5)"


def is_sleap_analysis(path: Path) -> bool:
    """Whether the HDF5 file `path` holds SLEAP's analysis datasets (False for other or unreadable files)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "tracks" in f and "node_names" in f and isinstance(f["tracks"], h5py.Dataset)
    except (OSError, ValueError, RuntimeError):  # h5py raises RuntimeError for a damaged file's structures
        return False


def read_sleap_analysis(
    path: Path, video: str, person: int | None = None, every_person: bool = False
) -> list[Detection]:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            dims = _dims(path, f)
            tracks = _ordered(path, np.asarray(f["tracks"][()], dtype=float), dims, CANONICAL)
            nodes = [_text(n) for n in f["node_names"][()]]
            names = [_text(n) for n in f["track_names"][()]] if "track_names" in f else []
            scores = None
            if "point_scores" in f:
                score_dims = tuple(d for d in dims if d != "xy")
                scores = _ordered(path, np.asarray(f["point_scores"][()], dtype=float), score_dims, CANONICAL[:3])
    except InputError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as error:
        raise InputError(path, f"not a readable SLEAP analysis HDF5 file ({error})", fix=EXPORT_FIX) from None
    _, n_tracks, n_nodes, _ = tracks.shape
    if n_nodes != len(nodes):
        raise InputError(path, f"'tracks' has {n_nodes} nodes but 'node_names' {len(nodes)}", fix=EXPORT_FIX)
    if scores is not None and scores.shape != tracks.shape[:3]:
        raise InputError(path, f"'point_scores' is {scores.shape}, 'tracks' {tracks.shape}", fix=EXPORT_FIX)
    if names and len(names) != n_tracks:
        raise InputError(path, f"'tracks' has {n_tracks} tracks but 'track_names' {len(names)}", fix=EXPORT_FIX)
    if n_tracks == 0:
        log.warning("%s: no tracks in it: nothing to import", path.name)
    # untracked instances (no track names): one slot keeps the bare node names, several are numbered
    track_names = names if names else [""] if n_tracks == 1 else _numbered(n_tracks)
    if len(set(track_names)) != len(track_names):
        raise InputError(path, f"track names repeat: {', '.join(track_names)}", fix="name SLEAP's tracks uniquely")
    counts = {
        (t, node): int(np.isfinite(tracks[:, k, n, 0]).sum())
        for k, t in enumerate(track_names)
        for n, node in enumerate(nodes)
    }
    named = individual_names(path, counts, person, every_person, word="tracks")
    detections: list[Detection] = []
    for k, t in enumerate(track_names):
        for n, node in enumerate(nodes):
            name = named[t, node]
            if name is None:
                continue
            xy = tracks[:, k, n, :]
            # NaN is SLEAP's "not found"; an infinite coordinate is no position (refused at import, not skipped)
            for frame in np.flatnonzero(~np.isnan(xy).any(axis=1)):
                score = None if scores is None or math.isnan(scores[frame, k, n]) else float(scores[frame, k, n])
                detections.append(
                    Detection(
                        video=video,
                        frame=int(frame),
                        point=name,
                        x=float(xy[frame, 0]),
                        y=float(xy[frame, 1]),
                        score=score,
                        where=f"{path.name}:frame {int(frame)}",
                    )
                )
    return detections


SLP_FORMATS = (1.1, 3.0)  # pixel centres from 1.1 (older: corners); 3.0 changed the tables (sleap-io refuses it too)
USER, PREDICTED = 0, 1  # instance_type


def read_sleap_slp(
    path: Path, video: str | None, person: int | None = None, every_person: bool = False
) -> list[Detection]:
    """The points of every video of a SLEAP .slp file (`video`: the name for a file of one video). Per frame and
    track one instance: the user's where there is one (SLEAP hides that track's predictions), else the prediction."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            format_id = float(f["metadata"].attrs.get("format_id", 0.0))
            if not SLP_FORMATS[0] <= format_id < SLP_FORMATS[1]:
                raise InputError(path, f"SLEAP file format {format_id:g} is not read", fix=EXPORT_FIX)
            if "video_crops" in f:
                raise InputError(path, "its videos are crops (points in crop coordinates)", fix=EXPORT_FIX)
            metadata = json.loads(_text(f["metadata"].attrs["json"]))
            tracks = [str(json.loads(_text(t))[1]) for t in f["tracks_json"][()]] if "tracks_json" in f else []
            videos = [_video_stem(json.loads(_text(v))) for v in f["videos_json"][()]]
            frames, instances = f["frames"][()], f["instances"][()]
            points = {USER: f["points"][()], PREDICTED: f["pred_points"][()]}
            plain = [n for n in ("frames", "instances", "points", "pred_points") if f[n].dtype.names is None]
            if plain:  # a newer writer's plain-array tables, not the named columns read here
                raise InputError(
                    path,
                    f"its {', '.join(plain)} tables are plain arrays, not the named columns of the SLEAP .slp layout "
                    f"read here (format {format_id:g})",
                    fix=EXPORT_FIX,
                )
    except InputError:
        raise
    except (OSError, KeyError, ValueError, TypeError, IndexError, RuntimeError) as error:
        raise InputError(path, f"not a readable SLEAP .slp file ({error})", fix=EXPORT_FIX) from None
    try:
        names = [str(n["name"]) for n in metadata["nodes"]]
        skeletons = [
            [names[int(n["id"])] for n in skeleton.get("nx_graph", skeleton)["nodes"]]
            for skeleton in metadata["skeletons"]
        ]
    except (KeyError, TypeError, ValueError, IndexError, AttributeError):
        raise InputError(
            path, "its skeletons are stored in a layout this reader does not know", fix=EXPORT_FIX
        ) from None
    if len(set(tracks)) != len(tracks):
        raise InputError(path, f"track names repeat: {', '.join(tracks)}", fix="name SLEAP's tracks uniquely")
    if video is not None:
        if len(videos) > 1:
            raise InputError(
                path,
                f"--video names one video, but the file holds {len(videos)} ({', '.join(v or '?' for v in videos)})",
                fix="leave --video out",
            )
        videos = [video]
    if any(not v for v in videos):
        raise InputError(path, "a video of the file has no file name (an embedded video?)", fix=EXPORT_FIX)
    if len(set(videos)) != len(videos):
        raise InputError(
            path, f"its videos' file names repeat ({', '.join(videos)})", fix="give each video its own name"
        )
    try:
        chosen, untracked = _chosen_instances(path, frames, instances, videos, tracked=bool(tracks))
        if untracked:
            log.warning(
                "%s: %d untracked instances beside the tracked ones are left out (no track tells who they are)",
                path.name,
                untracked,
            )
        # per video: (track index or -1, node) -> frame -> (x, y, score)
        found: dict[int, dict[tuple[int, str], dict[int, tuple[float, float, float | None]]]] = {}
        for (v, frame, track), instance in chosen.items():
            kind = int(instance["instance_type"])
            rows = points[kind][int(instance["point_id_start"]) : int(instance["point_id_end"])]
            nodes = skeletons[int(instance["skeleton"])]
            scored = kind == PREDICTED and "score" in (rows.dtype.names or ())
            for node, point in zip(nodes, rows, strict=True):
                x, y = float(point["x"]), float(point["y"])
                if not bool(point["visible"]) or not (math.isfinite(x) and math.isfinite(y)):
                    continue
                score = float(point["score"]) if scored and math.isfinite(float(point["score"])) else None
                found.setdefault(v, {}).setdefault((track, node), {})[frame] = (x, y, score)
    except InputError:
        raise
    except (KeyError, IndexError, ValueError, TypeError) as error:
        raise InputError(
            path, f"its instances do not fit its frames, skeletons or points ({error})", fix=EXPORT_FIX
        ) from None
    detections: list[Detection] = []
    for v, per_point in sorted(found.items()):
        keys = sorted(per_point, key=lambda key: key[0])  # the file's track order: ties in --person follow it
        labelled = [(tracks[t] if t >= 0 else "", node) for t, node in keys]
        counts = {label: len(per_point[key]) for key, label in zip(keys, labelled, strict=True)}
        named = individual_names(path, counts, person, every_person, word="tracks")
        for key, label in zip(keys, labelled, strict=True):
            point = named[label]
            if point is None:
                continue
            for frame, (x, y, score) in sorted(per_point[key].items()):
                where = f"{path.name}:{videos[v]} frame {frame}"
                detections.append(
                    Detection(video=videos[v], frame=frame, point=point, x=x, y=y, score=score, where=where)
                )
    return detections


def _chosen_instances(
    path: Path, frames: np.ndarray, instances: np.ndarray, videos: list[str], tracked: bool
) -> tuple[dict[tuple[int, int, int], np.void], int]:
    """(video, frame, track index or -1) -> the instance to import: the user's where there is one, else the
    prediction; and how many untracked instances of a `tracked` file were left out. Two instances of one kind on one
    track and frame (or two untracked ones in an untracked file) are an error."""
    frame_of = {}
    for row in frames:
        v = int(row["video"])
        if not 0 <= v < len(videos):
            raise InputError(
                path, f"frame {int(row['frame_idx'])} refers to video {v} of {len(videos)}", fix=EXPORT_FIX
            )
        frame_of[int(row["frame_id"])] = (v, int(row["frame_idx"]))
    chosen: dict[tuple[int, int, int], np.void] = {}
    kinds: dict[tuple[int, int, int], int] = {}
    untracked = 0
    for instance in instances:
        kind = int(instance["instance_type"])
        if kind not in (USER, PREDICTED):
            continue
        v, frame = frame_of[int(instance["frame_id"])]
        track = int(instance["track"])
        if track < 0 and tracked:
            untracked += 1
            continue
        key = (v, frame, track)
        if key in kinds and kinds[key] == kind:
            what = f"track {track}" if track >= 0 else "no track"
            raise InputError(
                path,
                f"two {'user' if kind == USER else 'predicted'} instances with {what} on frame {frame} of {videos[v]}",
                fix="track them in SLEAP (sleap-track with a tracker), or keep one instance per track and frame",
            )
        if key not in kinds or kind == USER:  # the user's instance hides the track's prediction
            chosen[key], kinds[key] = instance, kind
    return chosen, untracked


def _video_stem(entry: dict[str, Any]) -> str:
    """A video's name from its videos_json entry: its file's stem (an image sequence: its folder's name; an embedded
    video: the source video's), "" where none is known."""
    backend = entry.get("backend") or {}
    for source in (
        backend.get("filename"),
        entry.get("filename"),
        (entry.get("source_video") or {}).get("backend", {}).get("filename"),
    ):
        if isinstance(source, str) and source.strip() not in ("", "."):
            return _stem(source)
    filenames = backend.get("filenames") or (entry.get("filename") if isinstance(entry.get("filename"), list) else None)
    return _path(str(filenames[0])).parent.name if filenames else ""


def video_name_from_sleap(path: Path) -> str:
    """The stem of the video the file was exported from (its `video_path` dataset, which SLEAP and sleap-io
    write), else the file name without `.analysis.h5` (SLEAP names its exports
    `<labels>.<index>_<video>.analysis.h5`: the video's stem follows the first `_`)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            source = _text(f["video_path"][()]) if "video_path" in f else ""
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):
        source = ""
    if source.strip():
        return _stem(source)
    name = path.name
    for suffix in (".analysis.h5", ".h5", ".hdf5"):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    exported = _EXPORT_NAME.fullmatch(name)
    if exported:
        return exported.group(1)
    for suffix in (".predictions", ".slp"):  # sleap-track writes <video>.predictions.slp
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
    return name or path.stem


def _path(source: str) -> PurePath:
    """A path written on POSIX or on Windows (SLEAP projects move between machines)."""
    return PureWindowsPath(source) if "\\" in source else PurePosixPath(source)


def _stem(source: str) -> str:
    """A video file's stem, from a POSIX or a Windows path."""
    return _path(source).stem


def _dims(path: Path, f: Any) -> tuple[str, ...]:
    attrs = f["tracks"].attrs
    if "dims" in attrs:
        try:
            dims = tuple(str(d) for d in json.loads(_text(attrs["dims"])))
        except (ValueError, TypeError):
            raise InputError(
                path, f"'tracks' dims attribute {attrs['dims']!r} is not a JSON list", fix=EXPORT_FIX
            ) from None
        if sorted(dims) != sorted(CANONICAL):
            raise InputError(
                path, f"'tracks' dims {list(dims)}, expected {list(CANONICAL)} in some order", fix=EXPORT_FIX
            )
        return dims
    return MATLAB if bool(f.attrs.get("transpose", True)) else LEGACY_UNTRANSPOSED


def _ordered(path: Path, array: np.ndarray, dims: tuple[str, ...], target: tuple[str, ...]) -> np.ndarray:
    if array.ndim != len(dims):
        raise InputError(
            path, f"an array of {array.ndim} axes where {len(dims)} ({', '.join(dims)}) were expected", fix=EXPORT_FIX
        )
    out = np.transpose(array, [dims.index(d) for d in target])
    if "xy" in target and out.shape[-1] != 2:
        raise InputError(path, f"'tracks' has {out.shape[-1]} coordinates per point, expected 2 (x, y)", fix=EXPORT_FIX)
    return out


def _text(value: object) -> str:
    return value.decode("utf-8") if isinstance(value, bytes | np.bytes_) else str(value)


def _numbered(n: int) -> list[str]:
    return [f"track_{k}" for k in range(n)]
