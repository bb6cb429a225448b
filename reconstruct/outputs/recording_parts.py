"""The parts of the rerun recording, one function per entity; each sends its rows in batches.

Everything time-varying goes through `send_columns`, one batch per (entity, video): per-row `log` calls cost far
more than the whole recording sent this way. See `reconstruct.outputs.recording` for the layout.
"""

from __future__ import annotations

import colorsys
import logging
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import rerun as rr

from reconstruct.outputs.points import FramePoints
from sfm.cameras import CameraSet, VideoCameras
from tracking.tracks import Tracks

log = logging.getLogger(__name__)
MAX_PREROLL = 60  # container samples before the first decoded frame searched when matching frames to samples

POINTS_CLASS_ID = 0
Columns = Iterable[rr.ComponentColumn]
GlobalTimes = dict[tuple[str, int], float]  # (video, frame) -> estimated global time, seconds
# Track colours by `source`: what a person clicked must stand out from what the tracker produced.
LABEL_COLOR = (255, 255, 255)
TRACK_COLOR = (0, 200, 255)
OTHER_SOURCE_COLOR = (255, 170, 0)


def point_colors(num_points: int) -> np.ndarray:
    """(P, 3) uint8 distinct colours: golden-ratio hue steps, so point i keeps its colour whatever P is."""
    hues = (np.arange(num_points) * 0.618033988749895) % 1.0
    rgb = [colorsys.hsv_to_rgb(h, 0.85, 0.95) for h in hues]
    return (np.array(rgb).reshape(-1, 3) * 255).round().astype(np.uint8)


def entity_part(name: str) -> str:
    """A video name as one entity path part (names may contain '/', spaces, ...)."""
    return str(rr.escape_entity_path_part(name))


def camera_entity(video: str) -> str:
    return f"world/cameras/{entity_part(video)}"


def frame_timeline(video: str) -> str:
    return f"frame:{video}"


# -----------------------------------------------------------------------------------------------------------
# Batch logging helpers


def send_rows(
    rec: rr.RecordingStream,
    entity: str,
    video: str,
    frames: np.ndarray,
    gtime: np.ndarray | None,
    columns_for: Callable[[np.ndarray], Columns],
) -> None:
    """Send one batch of rows of `video`, on `frame:<video>` and, where finite, on `global_time`.

    `columns_for(mask)` returns the component columns of the rows selected by the boolean mask (F_v,).
    send_columns needs every index column to cover every row, so rows with and without a global time go in
    separate batches.
    """
    groups = [(np.ones(len(frames), dtype=bool), False)]
    if gtime is not None:
        known = np.isfinite(gtime)
        groups = [(known, True), (~known, False)]
    for mask, with_time in groups:
        if not mask.any():
            continue
        indexes = [rr.TimeColumn(frame_timeline(video), sequence=frames[mask])]
        if with_time and gtime is not None:
            indexes.append(rr.TimeColumn("global_time", duration=gtime[mask]))
        rec.send_columns(entity, indexes=indexes, columns=columns_for(mask))


def row_slices(lengths: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Flat element indices of the rows selected by mask, for rows of the given lengths laid end to end."""
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    chosen = [np.arange(s, s + n) for s, n in zip(starts[mask], lengths[mask], strict=True)]
    return np.concatenate(chosen) if chosen else np.zeros(0, dtype=np.int64)


# -----------------------------------------------------------------------------------------------------------
# Geometry


def project(
    X: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, dist: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points with OpenCV's model (and distortion) in pixels.

    X: (F, P, 3); K, R: (F, 3, 3); t: (F, 3); dist: (F, 4), (F, 5) or (F, 8): k1, k2, p1, p2, k3, k4, k5, k6
    (OpenCV's rational model), or None.
    Returns uv (F, P, 2) and in_front (F, P) bool (depth > 0 and finite).
    """
    Xc = np.einsum("fij,fpj->fpi", R, X) + t[:, None, :]
    z = Xc[..., 2]
    in_front = np.isfinite(z) & (z > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = Xc[..., 0] / z
        y = Xc[..., 1] / z
    if dist is not None:
        dist = np.pad(dist, ((0, 0), (0, 8 - dist.shape[1])))  # 4 or 5 coefficients: the rest are 0
        k1, k2, p1, p2, k3, k4, k5, k6 = (dist[:, i, None] for i in range(8))
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        x, y = (
            x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
        )
    u = K[:, 0, 0, None] * x + K[:, 0, 1, None] * y + K[:, 0, 2, None]
    v = K[:, 1, 1, None] * y + K[:, 1, 2, None]
    return np.stack([u, v], axis=-1), in_front


def auto_plane_distance(cameras: CameraSet, points: FramePoints) -> float:
    """A frustum size in world units: 1/10 of the median camera-to-points distance."""
    centers = np.array([f.center for v in cameras.videos for f in v.frames]).reshape(-1, 3)
    finite = points.xyz[np.isfinite(points.xyz).all(axis=-1)]
    if len(centers) == 0:
        return 1.0
    if len(finite) == 0:
        spread = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max(initial=0.0))
        return 0.1 * spread if spread > 0 else 1.0
    distance = float(np.median(np.linalg.norm(centers - np.median(finite, axis=0), axis=1)))
    return 0.1 * distance if distance > 0 else 1.0


# -----------------------------------------------------------------------------------------------------------
# The parts of the recording


def log_world(
    rec: rr.RecordingStream,
    point_names: Sequence[str],
    skeleton: Sequence[tuple[str, str]] | None,
    colors: np.ndarray,
    axes: rr.components.ViewCoordinates,
) -> None:
    """`world`: the axes convention and the annotation context (colour, label, bones of every point)."""
    rec.log("world", axes, static=True)
    index = {name: i for i, name in enumerate(point_names)}
    connections = [(index[a], index[b]) for a, b in skeleton or ()]
    rec.log(
        "world",
        rr.AnnotationContext(
            [
                rr.ClassDescription(
                    info=rr.AnnotationInfo(id=POINTS_CLASS_ID, label="points"),
                    keypoint_annotations=[
                        rr.AnnotationInfo(id=i, label=name, color=tuple(int(c) for c in colors[i]))
                        for i, name in enumerate(point_names)
                    ],
                    keypoint_connections=connections,
                )
            ]
        ),
        static=True,
    )


def log_points(rec: rr.RecordingStream, points: FramePoints, gtime_all: np.ndarray | None, radius: float) -> None:
    """`world/points`: the finite points of every frame, with keypoint ids (colour, bones) and names."""
    P = len(points.point_names)
    names = np.array(points.point_names, dtype=object)
    videos = np.array(points.videos, dtype=object)
    for video in dict.fromkeys(points.videos):
        rows = np.flatnonzero(videos == video)
        xyz = points.xyz[rows]
        finite = np.isfinite(xyz).all(axis=-1)  # (F_v, P)
        lengths = finite.sum(axis=1)
        ids = np.broadcast_to(np.arange(P), finite.shape)[finite]
        flat = xyz[finite]

        def columns(
            mask: np.ndarray, flat: np.ndarray = flat, ids: np.ndarray = ids, lengths: np.ndarray = lengths
        ) -> Columns:
            sel = row_slices(lengths, mask)
            n = len(sel)
            return list(
                rr.Points3D.columns(
                    positions=flat[sel],
                    keypoint_ids=ids[sel].astype(np.uint16),
                    class_ids=np.full(n, POINTS_CLASS_ID, np.uint16),
                    labels=names[ids[sel]].tolist(),
                    radii=np.full(n, -radius, np.float32),  # negative = UI points
                ).partition(lengths[mask])
            )

        send_rows(
            rec,
            "world/points",
            video,
            points.frames[rows].astype(np.int64),
            None if gtime_all is None else gtime_all[rows],
            columns,
        )


def video_global_time(video: VideoCameras, frames: np.ndarray, lookup: GlobalTimes | None) -> np.ndarray | None:
    """(n,) global time of these frames of `video`, NaN where unknown; None without global times."""
    if lookup is None:
        return None
    return np.array([lookup.get((video.name, int(f)), np.nan) for f in frames])


def log_camera(rec: rr.RecordingStream, video: VideoCameras, lookup: GlobalTimes | None, plane_distance: float) -> None:
    """`world/cameras/<video>`: Pinhole (static when K is constant) and cam_from_world of each posed frame."""
    entity = camera_entity(video.name)
    frames_sorted = sorted(video.frames, key=lambda f: f.frame)
    if not frames_sorted:
        return
    numbers = np.array([f.frame for f in frames_sorted], dtype=np.int64)
    K = np.array([f.K for f in frames_sorted], dtype=float)
    R = np.array([f.R for f in frames_sorted], dtype=float)
    t = np.array([f.t for f in frames_sorted], dtype=float)
    gtime = video_global_time(video, numbers, lookup)
    resolution = [video.width, video.height]
    if np.allclose(K, K[0]):
        # One intrinsic matrix for the whole video (the usual case): static, so it shows on every timeline.
        rec.log(
            entity,
            rr.Pinhole(image_from_camera=K[0], resolution=resolution, image_plane_distance=plane_distance),
            static=True,
        )
    else:
        rec.log(entity, rr.Pinhole.from_fields(resolution=resolution, image_plane_distance=plane_distance), static=True)
        send_rows(rec, entity, video.name, numbers, gtime, lambda m: rr.Pinhole.columns(image_from_camera=K[m]))
    send_rows(
        rec,
        entity,
        video.name,
        numbers,
        gtime,
        lambda m: rr.Transform3D.columns(
            translation=t[m], mat3x3=R[m], relation=[rr.TransformRelation.ChildFromParent] * int(m.sum())
        ),
    )


def log_reprojection(
    rec: rr.RecordingStream, cameras: CameraSet, points: FramePoints, gtime_all: np.ndarray | None, radius: float
) -> None:
    """`world/cameras/<video>/image/reprojection`: each frame's 3D points projected by its own camera."""
    P = len(points.point_names)
    videos = np.array(points.videos, dtype=object)
    for video in dict.fromkeys(points.videos):
        cams = {f.frame: f for f in cameras.video(video).frames}
        rows = np.flatnonzero(videos == video)
        frame_cams = [cams[int(points.frames[i])] for i in rows]
        K = np.array([c.K for c in frame_cams], dtype=float)
        R = np.array([c.R for c in frame_cams], dtype=float)
        t = np.array([c.t for c in frame_cams], dtype=float)
        dist = None
        if any(c.dist is not None for c in frame_cams):
            dist = np.zeros((len(rows), 8))
            for j, c in enumerate(frame_cams):
                if c.dist is not None:
                    dist[j, : len(c.dist)] = c.dist
        uv, in_front = project(points.xyz[rows], K, R, t, dist)
        shown = in_front & np.isfinite(uv).all(axis=-1)
        lengths = shown.sum(axis=1)
        ids = np.broadcast_to(np.arange(P), shown.shape)[shown]
        flat = uv[shown]

        def columns(
            mask: np.ndarray, flat: np.ndarray = flat, ids: np.ndarray = ids, lengths: np.ndarray = lengths
        ) -> Columns:
            sel = row_slices(lengths, mask)
            n = len(sel)
            return list(
                rr.Points2D.columns(
                    positions=flat[sel],
                    keypoint_ids=ids[sel].astype(np.uint16),
                    class_ids=np.full(n, POINTS_CLASS_ID, np.uint16),
                    radii=np.full(n, -radius, np.float32),
                ).partition(lengths[mask])
            )

        entity = f"{camera_entity(video)}/image/reprojection"
        send_rows(
            rec,
            entity,
            video,
            points.frames[rows].astype(np.int64),
            None if gtime_all is None else gtime_all[rows],
            columns,
        )


def track_colors(tracks: Tracks) -> np.ndarray:
    """(N, 3) uint8 colour of each observation by its `source` column (label / track / other)."""
    colors = np.tile(np.array(TRACK_COLOR, np.uint8), (len(tracks), 1))
    source = tracks.extra.get("source")
    if source is not None:
        kind = np.array([s.strip().lower() for s in source], dtype=object)
        colors[kind == "label"] = LABEL_COLOR
        colors[(kind != "label") & (kind != "track")] = OTHER_SOURCE_COLOR
    return colors


def log_tracks(
    rec: rr.RecordingStream, cameras: CameraSet, tracks: Tracks, lookup: GlobalTimes | None, radius: float
) -> None:
    """`world/cameras/<video>/image/tracks`: the 2D observations, coloured by their `source`."""
    known = {v.name for v in cameras.videos}
    all_colors = track_colors(tracks)
    track_videos = np.array(tracks.video, dtype=object)
    track_points = np.array(tracks.point, dtype=object)
    for video in tracks.video_names():
        if video not in known:
            log.warning("tracks of video %r not recorded: no camera for that video", video)
            continue
        rows = np.flatnonzero(track_videos == video)
        rows = rows[np.argsort(tracks.frame[rows], kind="stable")]
        frame_of_row = tracks.frame[rows]
        numbers, lengths = np.unique(frame_of_row, return_counts=True)
        xy = tracks.xy[rows]
        labels = track_points[rows]
        colors = all_colors[rows]

        def columns(
            mask: np.ndarray,
            xy: np.ndarray = xy,
            labels: np.ndarray = labels,
            colors: np.ndarray = colors,
            lengths: np.ndarray = lengths,
        ) -> Columns:
            sel = row_slices(lengths, mask)
            return list(
                rr.Points2D.columns(
                    positions=xy[sel],
                    colors=colors[sel],
                    labels=labels[sel].tolist(),
                    radii=np.full(len(sel), -radius, np.float32),
                ).partition(lengths[mask])
            )

        gtime = None if lookup is None else np.array([lookup.get((video, int(f)), np.nan) for f in numbers])
        send_rows(rec, f"{camera_entity(video)}/image/tracks", video, numbers.astype(np.int64), gtime, columns)


def log_video(rec: rr.RecordingStream, video: VideoCameras, file: Path, lookup: GlobalTimes | None) -> None:
    """Embed the video file and reference its frame of every posed frame (the image under the camera)."""
    entity = f"{camera_entity(video.name)}/image"
    try:
        asset = rr.AssetVideo(path=file)
        timestamps = np.asarray(asset.read_frame_timestamps_nanos(), dtype=np.int64)
    except (OSError, RuntimeError, ValueError) as error:
        # A recording without the images is still useful; say why they are missing instead of failing.
        log.warning(
            "%s: video not embedded in the recording (%s); rerun plays H.264/H.265/AV1/VP8/VP9 "
            "in .mp4, re-encode e.g. OpenCV's mp4v as vp09",
            file,
            error,
        )
        return
    frames = sorted(video.frames, key=lambda f: f.frame)
    numbers = np.array([f.frame for f in frames], dtype=np.int64)
    samples = _video_samples(timestamps, numbers, [f.time for f in frames])
    beyond = samples < 0
    if beyond.any():
        log.warning(
            "%s has %d frames but cameras.json poses frame %d of video %r: those have no image",
            file,
            len(timestamps),
            int(numbers[beyond][0]),
            video.name,
        )
        numbers, samples = numbers[~beyond], samples[~beyond]
    rec.log(entity, asset, static=True)
    if len(numbers) == 0:
        return
    refs = timestamps[samples]

    def columns(mask: np.ndarray) -> Columns:
        return rr.VideoFrameReference.columns_nanos(refs[mask])

    send_rows(rec, entity, video.name, numbers, video_global_time(video, numbers, lookup), columns)


def _video_samples(timestamps: np.ndarray, numbers: np.ndarray, times: list[float | None]) -> np.ndarray:
    """(F,) the video file's sample of each decoded frame `numbers` (F,) (-1 = none). A container may hold samples
    the decoder never shows (an edit list's preroll after a stream-copy trim, damaged frames), so a frame's number
    is not its sample's: with decoder times, the frames are matched to the samples by time, the samples' start
    chosen where the most frames land on a sample; without, sample n is frame n."""
    by_number = np.where(numbers < len(timestamps), numbers, -1)
    if len(timestamps) < 2 or any(t is None for t in times):
        return by_number
    t = np.array(times, dtype=float)  # seconds from the first decoded frame
    ts = (timestamps - timestamps[0]) / 1e9
    step = float(np.median(np.diff(ts)))
    best, best_hits = by_number, -1
    for start in ts[: MAX_PREROLL + 1]:
        index = np.clip(np.searchsorted(ts, t + start - 0.5 * step), 0, len(ts) - 1)
        hits = np.abs(ts[index] - (t + start)) <= 0.25 * step
        if hits.sum() > best_hits:
            best, best_hits = np.where(hits, index, -1), int(hits.sum())
    return best if best_hits >= 0.5 * len(numbers) else by_number


def log_residual(
    rec: rr.RecordingStream, points: FramePoints, residual: np.ndarray, gtime_all: np.ndarray | None
) -> None:
    """`metrics/residual`: one scalar per frame; NaN frames are left out."""
    videos = np.array(points.videos, dtype=object)
    values = np.asarray(residual, dtype=float)
    for video in dict.fromkeys(points.videos):
        rows = np.flatnonzero(videos == video)
        rows = rows[np.isfinite(values[rows])]  # an unknown residual is a gap in the plot, not a zero
        if len(rows) == 0:
            continue

        def columns(mask: np.ndarray, vals: np.ndarray = values[rows]) -> Columns:
            return rr.Scalars.columns(scalars=vals[mask])

        send_rows(
            rec,
            "metrics/residual",
            video,
            points.frames[rows].astype(np.int64),
            None if gtime_all is None else gtime_all[rows],
            columns,
        )
