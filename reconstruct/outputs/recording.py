"""The rerun recording of a reconstruction (`recording.rrd`): 3D points, cameras, 2D tracks and reprojections.

Entity paths mirror the scene (see docs/formats.md#recordingrrd):

    world                                  ViewCoordinates (static; RIGHT_HAND_Y_DOWN unless options say
                                           otherwise) + AnnotationContext: colour, label, bones (static)
    world/background                       Points3D, static scene cloud (when given)
    world/points                           Points3D per frame, colour and label per point; skeleton lines
    world/cameras/<video>                  Transform3D cam_from_world + Pinhole, per frame of that video
    world/cameras/<video>/image            AssetVideo + VideoFrameReference per posed frame (when given)
    world/cameras/<video>/image/tracks     Points2D, 2D observations (labels and tracked points differ)
    world/cameras/<video>/image/reprojection   Points2D, the 3D points projected into that frame
    metrics/residual                       Scalars, per-frame residual

Timelines: `frame:<video>` (sequence, that video's decoded frame index) on every row of that video, plus
`global_time` (duration, seconds) on every row whose frame has an estimated global time. The entities are
logged by `reconstruct.outputs.recording_parts`, in batches (`send_columns`).
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from dynrecon.atomic import publish
from dynrecon.errors import InputError
from reconstruct.outputs import recording_parts as parts
from reconstruct.outputs.points import FramePoints
from reconstruct.outputs.recording_options import RecordingOptions, WorldAxes
from reconstruct.outputs.recording_parts import camera_entity
from sfm.cameras import CameraSet
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

APPLICATION_ID = "dynrecon"


# Display sizes in UI points (screen size), so they do not depend on the world's units.
POINT_RADIUS = 5.0
TRACK_RADIUS = 5.0
REPROJECTION_RADIUS = 3.0
BACKGROUND_RADIUS = 1.5

VIEW_COORDINATES = {
    WorldAxes.Y_DOWN: rr.ViewCoordinates.RIGHT_HAND_Y_DOWN,
    WorldAxes.Z_UP: rr.ViewCoordinates.RIGHT_HAND_Z_UP,
    WorldAxes.Y_UP: rr.ViewCoordinates.RIGHT_HAND_Y_UP,
}


@dataclass(kw_only=True)
class BackgroundCloud:
    """The static scene (e.g. COLMAP's sparse points)."""

    xyz: np.ndarray  # (N, 3) world coordinates
    colors: np.ndarray | None = None  # (N, 3) uint8 RGB


# -----------------------------------------------------------------------------------------------------------
# Input checks


def _check_inputs(
    cameras: CameraSet,
    points: FramePoints,
    skeleton: Sequence[tuple[str, str]] | None,
    residual: np.ndarray | None,
    global_time: np.ndarray | None,
) -> None:
    F, P = points.num_frames, len(points.point_names)
    if points.xyz.shape != (F, P, 3) or points.observed.shape != (F, P) or len(points.frames) != F:
        raise InputError(
            None,
            f"points: xyz {points.xyz.shape}, observed {points.observed.shape} and "
            f"{len(points.frames)} frames do not match {F} frames x {P} points",
        )
    posed = {(v.name, f.frame) for v in cameras.videos for f in v.frames}
    for video, frame in zip(points.videos, points.frames, strict=True):
        if (video, int(frame)) not in posed:
            raise InputError(
                None,
                f"points of video {video!r} frame {int(frame)} have no camera",
                fix="points3d.csv and cameras.json must come from the same run",
            )
    for name, values in (("residual", residual), ("global_time", global_time)):
        if values is not None and np.shape(values) != (F,):
            raise InputError(None, f"{name} has shape {np.shape(values)}, expected ({F},): one per frame")
    known = set(points.point_names)
    for a, b in skeleton or ():
        for name in (a, b):
            if name not in known:
                raise InputError(
                    None,
                    f"skeleton bone ({a!r}, {b!r}) names unknown point {name!r}",
                    fix="bones must join point names of points3d.csv",
                )


# -----------------------------------------------------------------------------------------------------------
# Public API


def build_blueprint(cameras: CameraSet, *, residual: bool, global_time: bool) -> rrb.Blueprint:
    """3D view of `world`, one 2D view per camera's image space, the residual plot below."""
    camera_views = [rrb.Spatial2DView(origin=camera_entity(v.name), name=v.name) for v in cameras.videos]
    right: list[rrb.Container | rrb.View] = list(camera_views)
    if residual:
        right.append(rrb.TimeSeriesView(origin="metrics", name="residual"))
    main = rrb.Spatial3DView(origin="world", name="3D")
    layout: rrb.Container | rrb.View = (
        rrb.Horizontal(main, rrb.Vertical(*right), column_shares=[2, 1]) if right else main
    )
    parts: list = [layout]
    if global_time:
        parts.append(rrb.TimePanel(timeline="global_time"))
    return rrb.Blueprint(*parts, collapse_panels=False)


def log_recording(
    rec: rr.RecordingStream,
    *,
    cameras: CameraSet,
    points: FramePoints,
    tracks: Tracks | None = None,
    skeleton: Sequence[tuple[str, str]] | None = None,
    residual: np.ndarray | None = None,
    global_time: np.ndarray | None = None,
    background: BackgroundCloud | None = None,
    video_files: Mapping[str, str | Path] | None = None,
    options: RecordingOptions | None = None,
) -> None:
    """Log a whole reconstruction into `rec` (any sink: file, viewer, memory).

    cameras: every posed frame. points: frame i is (points.videos[i], points.frames[i]), xyz (F, P, 3) with
    NaN = not reconstructed. tracks: 2D observations, optional column `source` = label | track.
    skeleton: bones as pairs of point names. residual: (F,) per-frame residual (NaN = unknown).
    global_time: (F,) estimated global time in seconds (NaN = unknown). background: static scene cloud.
    video_files: video name -> its file, embedded as the camera's image (only codecs rerun plays:
    H.264/H.265/AV1/VP8/VP9 in .mp4; others are skipped with a warning).
    Raises InputError when the inputs do not fit together.
    """
    options = options or RecordingOptions()
    _check_inputs(cameras, points, skeleton, residual, global_time)
    gtime_all = None if global_time is None else np.asarray(global_time, dtype=float)
    lookup = None
    if gtime_all is not None:
        lookup = {(v, int(f)): float(g) for v, f, g in zip(points.videos, points.frames, gtime_all, strict=True)}
    colors = parts.point_colors(len(points.point_names))
    parts.log_world(rec, points.point_names, skeleton, colors, VIEW_COORDINATES[options.world_axes])
    if background is not None and len(background.xyz):
        xyz = np.asarray(background.xyz, dtype=float).reshape(-1, 3)
        keep = np.isfinite(xyz).all(axis=1)
        rec.log(
            "world/background",
            rr.Points3D(
                xyz[keep],
                colors=None if background.colors is None else np.asarray(background.colors)[keep],
                radii=rr.Radius.ui_points(BACKGROUND_RADIUS),
            ),
            static=True,
        )
    plane = parts.auto_plane_distance(cameras, points)  # 1/10 of the median camera-point distance
    for video in cameras.videos:
        parts.log_camera(rec, video, lookup, plane)
    parts.log_points(rec, points, gtime_all, POINT_RADIUS)
    parts.log_reprojection(rec, cameras, points, gtime_all, REPROJECTION_RADIUS)
    if tracks is not None and len(tracks):
        parts.log_tracks(rec, cameras, tracks, lookup, TRACK_RADIUS)
    if residual is not None:
        parts.log_residual(rec, points, residual, gtime_all)
    for name, file in (video_files or {}).items():
        try:
            video = cameras.video(name)
        except KeyError:
            log.warning("video file %s not recorded: no camera for video %r", file, name)
            continue
        parts.log_video(rec, video, Path(file), lookup)


def write_recording(
    path: str | Path,
    *,
    cameras: CameraSet,
    points: FramePoints,
    tracks: Tracks | None = None,
    skeleton: Sequence[tuple[str, str]] | None = None,
    residual: np.ndarray | None = None,
    global_time: np.ndarray | None = None,
    background: BackgroundCloud | None = None,
    video_files: Mapping[str, str | Path] | None = None,
    options: RecordingOptions | None = None,
    recording_id: str | None = None,
) -> Path:
    """Write `path` (.rrd) with `log_recording`, atomically, with the default blueprint and a footer."""
    options = options or RecordingOptions()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _check_inputs(cameras, points, skeleton, residual, global_time)  # fail before creating any file
    start = time.perf_counter()
    blueprint = (
        build_blueprint(cameras, residual=residual is not None, global_time=global_time is not None)
        if options.blueprint
        else None
    )
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    try:
        rec.save(tmp, default_blueprint=blueprint)  # the sink must exist before the first log call
        log_recording(
            rec,
            cameras=cameras,
            points=points,
            tracks=tracks,
            skeleton=skeleton,
            residual=residual,
            global_time=global_time,
            background=background,
            video_files=video_files,
            options=options,
        )
        rec.disconnect()  # flushes and writes the footer, without which readers see a "legacy RRD"
        publish(tmp, path)
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    log.info(
        "wrote %s (%d frames, %d points) in %.2f s",
        path,
        points.num_frames,
        len(points.point_names),
        time.perf_counter() - start,
    )
    return path
