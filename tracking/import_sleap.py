"""SLEAP's files: its project / predictions files (.slp, `read_sleap_slp`) and its analysis HDF5
(`sleap-convert --format analysis`, or File > Export Analysis HDF5; sleap-io's `save_analysis_h5`): dense arrays of
every track's nodes over the video's frames (`read_sleap_analysis`).

Datasets: `tracks` (x, y; NaN = missing), `node_names`, `track_names`, optionally `point_scores`. Axis order: the
`dims` attribute of `tracks` where sleap-io wrote one (its `matlab` and `standard` presets), else SLEAP's own layout
(`transpose` true or absent: track, xy, node, frame; false: frame, node, xy, track). The frame axis starts at the
video's frame 0 (SLEAP's default `all_frames`; an export without it starts at the first labelled frame and does
not say which, so its frames would be shifted). SLEAP's tracks, like DeepLabCut's individuals, hold within a video:
`person` / `every_person` as in `tracking.people.individual_names`.

.slp (SLEAP format 1.2 and later, as SLEAP and sleap-io write it: HDF5 tables `frames`, `instances`, `points`,
`pred_points`, JSON `metadata`, `tracks_json`, `videos_json`): every video of the file is imported under its file's
stem; a user instance corrected from a prediction replaces it; points not visible are missing. Older or unknown
layouts are refused with the export command.
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path, PureWindowsPath
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
    except (OSError, ValueError):
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
    except (OSError, KeyError, ValueError, TypeError) as error:
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
    seen = {t: int(np.isfinite(tracks[:, k, :, 0]).sum()) for k, t in enumerate(track_names)}
    points = [(t, node) for t in track_names for node in nodes]
    named = individual_names(path, points, seen, person, every_person, word="tracks")
    detections: list[Detection] = []
    for k, t in enumerate(track_names):
        for n, node in enumerate(nodes):
            name = named[t, node]
            if name is None:
                continue
            xy = tracks[:, k, n, :]
            for frame in np.flatnonzero(np.isfinite(xy).all(axis=1)):
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


MIN_SLP_FORMAT = 1.2  # instances with a tracking score: SLEAP 1.1 onwards (older files: pixel corners, not centres)
USER, PREDICTED = 0, 1  # instance_type


def read_sleap_slp(
    path: Path, video: str | None, person: int | None = None, every_person: bool = False
) -> list[Detection]:
    """The points of every video of a SLEAP .slp file (`video`: the name for a file of one video)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            format_id = float(f["metadata"].attrs.get("format_id", 0.0))
            if format_id < MIN_SLP_FORMAT:
                raise InputError(
                    path, f"SLEAP file format {format_id:g} is older than {MIN_SLP_FORMAT}", fix=EXPORT_FIX
                )
            metadata = json.loads(_text(f["metadata"].attrs["json"]))
            tracks = [str(json.loads(_text(t))[1]) for t in f["tracks_json"][()]] if "tracks_json" in f else []
            videos = [_video_stem(json.loads(_text(v)), k) for k, v in enumerate(f["videos_json"][()])]
            frames, instances = f["frames"][()], f["instances"][()]
            points = {USER: f["points"][()], PREDICTED: f["pred_points"][()]}
    except InputError:
        raise
    except (OSError, KeyError, ValueError, TypeError, IndexError) as error:
        raise InputError(path, f"not a readable SLEAP .slp file ({error})", fix=EXPORT_FIX) from None
    try:
        names = [str(n["name"]) for n in metadata["nodes"]]
        skeletons = [[names[int(n["id"])] for n in skeleton["nodes"]] for skeleton in metadata["skeletons"]]
    except (KeyError, TypeError, ValueError, IndexError):
        raise InputError(
            path, "its skeletons are stored in a layout this reader does not know", fix=EXPORT_FIX
        ) from None
    if video is not None and len(videos) > 1:
        raise InputError(
            path,
            f"--video names one video, but the file holds {len(videos)} ({', '.join(videos)})",
            fix="leave --video out",
        )
    if video is not None:
        videos = [video]
    if len(set(videos)) != len(videos):
        raise InputError(
            path, f"its videos' file names repeat ({', '.join(videos)})", fix="give each video its own name"
        )
    # per video: (track name or "", node) -> frame -> (x, y, score); user instances first, replacing their predictions
    found: dict[int, dict[tuple[str, str], dict[int, tuple[float, float, float | None]]]] = {}
    replaced = {
        int(i["from_predicted"]) for i in instances if int(i["instance_type"]) == USER and int(i["from_predicted"]) >= 0
    }
    frame_of = {int(fr["frame_id"]): (int(fr["video"]), int(fr["frame_idx"])) for fr in frames}
    untracked: dict[tuple[int, int], int] = {}
    for instance in sorted(instances, key=lambda i: int(i["instance_type"]) != USER):
        kind = int(instance["instance_type"])
        if kind not in points or (kind == PREDICTED and int(instance["instance_id"]) in replaced):
            continue
        v, frame = frame_of[int(instance["frame_id"])]
        track = int(instance["track"])
        name = tracks[track] if 0 <= track < len(tracks) else ""
        if not name:
            untracked[v, frame] = untracked.get((v, frame), 0) + 1
            if untracked[v, frame] > 1:
                raise InputError(
                    path,
                    f"several untracked instances on frame {frame} of {videos[v]}",
                    fix="track them in SLEAP (sleap-track with a tracker), or keep one instance per frame",
                )
        rows = points[kind][int(instance["point_id_start"]) : int(instance["point_id_end"])]
        nodes = skeletons[int(instance["skeleton"])]
        for node, point in zip(nodes, rows, strict=False):
            x, y = float(point["x"]), float(point["y"])
            if not bool(point["visible"]) or not (math.isfinite(x) and math.isfinite(y)):
                continue
            score = float(point["score"]) if kind == PREDICTED and "score" in (rows.dtype.names or ()) else None
            found.setdefault(v, {}).setdefault((name, node), {}).setdefault(frame, (x, y, score))
    detections: list[Detection] = []
    for v, per_point in sorted(found.items()):
        seen: dict[str, int] = {}
        for (individual, _), per_frame in per_point.items():
            seen[individual] = seen.get(individual, 0) + len(per_frame)
        named = individual_names(path, list(per_point), seen, person, every_person, word="tracks")
        for key, per_frame in per_point.items():
            point = named[key]
            if point is None:
                continue
            for frame, (x, y, score) in sorted(per_frame.items()):
                where = f"{path.name}:{videos[v]} frame {frame}"
                detections.append(
                    Detection(video=videos[v], frame=frame, point=point, x=x, y=y, score=score, where=where)
                )
    return detections


def _video_stem(entry: dict[str, Any], k: int) -> str:
    source = entry.get("backend", {}).get("filename") or entry.get("filename") or ""
    if isinstance(source, list):  # an image sequence: its first image's folder
        source = str(Path(str(source[0])).parent) if source else ""
    return _stem(str(source)) or f"video{k}"


def video_name_from_sleap(path: Path) -> str:
    """The stem of the video the file was exported from (its `video_path` dataset, which SLEAP and sleap-io
    write), else the file name without `.analysis.h5` (SLEAP names its exports
    `<labels>.<index>_<video>.analysis.h5`: the video's stem follows the first `_`)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            source = _text(f["video_path"][()]) if "video_path" in f else ""
    except (OSError, KeyError, ValueError, TypeError):
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


def _stem(source: str) -> str:
    """A video file's stem, from a POSIX or a Windows path (SLEAP projects move between machines)."""
    return PureWindowsPath(source).stem if "\\" in source else Path(source).stem


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
