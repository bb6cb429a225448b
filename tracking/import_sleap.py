"""SLEAP's analysis HDF5 (`sleap-convert --format analysis`, or File > Export Analysis HDF5; sleap-io's
`save_analysis_h5`): dense arrays of every track's nodes over the video's frames.

Datasets: `tracks` (x, y; NaN = missing), `node_names`, `track_names`, optionally `point_scores`. Axis order: the
`dims` attribute of `tracks` where sleap-io wrote one (its `matlab` and `standard` presets), else SLEAP's own layout
(`transpose` true or absent: track, xy, node, frame; false: frame, node, xy, track). The frame axis starts at the
video's frame 0 (SLEAP's default `all_frames`; an export without it starts at the first labelled frame and does
not say which, so its frames would be shifted). SLEAP's tracks, like DeepLabCut's individuals, hold within a video:
`person` / `every_person` as in `tracking.people.individual_names`.

SLEAP's own project files (.slp) change layout with its versions and are not read: export the analysis HDF5.
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
        return PureWindowsPath(source).stem if "\\" in source else Path(source).stem
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
