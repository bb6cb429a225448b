"""The subject path with posed videos: the static cameras solved alone, moved onto the posed videos' world by one
similarity (`sfm.subject.posed`), then one bundle adjustment of the static cameras, every clock offset and the
trajectory against all the tracks, the posed videos' frames held at their poses."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from sfm.subject.bundle import Bundle, adjust, residuals_px, rotation, supported
from sfm.subject.calibrate import _thinned, calibrate_from_subject, rotation_vector
from sfm.subject.chain import Knots
from sfm.subject.model import (
    MIN_INLIERS,
    SubjectCalibrationError,
    SubjectOptions,
    SubjectResult,
    SubjectVideo,
    max_residual_px,
)
from sfm.subject.observations import VideoObs, build_observations, normalize
from sfm.subject.posed import Alignment, PosedVideo, align_to_posed, in_order, observed
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


def solve_with_posed(
    tracks: Tracks, videos: list[SubjectVideo], posed: list[PosedVideo], options: SubjectOptions
) -> tuple[SubjectResult, Alignment]:
    """Static cameras posed from `tracks` in the posed videos' world (frame and scale). Raises
    SubjectCalibrationError when the data cannot (the message says why)."""
    result = calibrate_from_subject(tracks, [dataclasses.replace(v, cam_from_world=None) for v in videos], options)
    points = list(result.points)
    # static videos with a known pose (the background's) take part in the alignment as posed videos too
    anchors = [_static_posed(v, tracks, result, points) for v in videos if v.cam_from_world is not None]
    alignment = align_to_posed(result, posed + [a for a in anchors if a is not None], options.max_offset)
    alignment.apply(result)
    adjust_with_posed(tracks, videos, result, posed, alignment)
    return result, alignment


def _static_posed(video: SubjectVideo, tracks: Tracks, result: SubjectResult, points: list[str]) -> PosedVideo | None:
    """A static video with a known pose, as a posed video at the subject path's offset (None: not posed by it)."""
    camera = result.camera(video.name)
    if camera is None or video.cam_from_world is None:
        return None
    F = len(video.times)
    R, t = video.cam_from_world
    return PosedVideo(
        name=video.name,
        times=np.asarray(video.times, dtype=float),
        R=np.broadcast_to(np.asarray(R, dtype=float), (F, 3, 3)).copy(),
        t=np.broadcast_to(np.asarray(t, dtype=float), (F, 3)).copy(),
        xy=normalize(observed(tracks, video.name, F, points), camera.K, camera.dist),
        focal=np.full(F, 0.5 * (camera.K[0, 0] + camera.K[1, 1])),
        points=points,
        offset=camera.offset,
        width=video.width,
        height=video.height,
    )


def adjust_with_posed(
    tracks: Tracks, videos: list[SubjectVideo], result: SubjectResult, posed: list[PosedVideo], alignment: Alignment
) -> None:
    """Bundle-adjust the aligned `result` with the posed videos' tracks (their frames held); updates `result` and
    `alignment.fits` in place. Raises SubjectCalibrationError when a video's tracks still disagree."""
    used = [f.name for f in alignment.fits if f.reason is None]
    anchors = [v for v in posed if v.name in used]
    by_name = {v.name: v for v in videos}
    statics = [
        dataclasses.replace(by_name[c.name], K=c.K, dist=c.dist, cam_from_world=None) for c in result.cameras
    ]  # intrinsics as solved: held
    static_names = {v.name for v in statics}
    # the videos the subject path posed (a refused one's rows are not "unknown"), columns in the trajectory's order
    found, obs = build_observations(tracks.of_videos(static_names), statics)
    points = list(result.points)
    for o in obs:
        o.xy, o.norm = in_order(o.xy, found, points), in_order(o.norm, found, points)
    obs += [_posed_obs(v, points) for v in anchors]
    offsets = np.array([c.offset for c in result.cameras] + [alignment.fit(v.name).offset for v in anchors])
    n = len(result.cameras)
    knots = Knots(
        t0=float(result.times[0]),
        h=float(result.times[1] - result.times[0]),
        X=np.stack([result.points[p] for p in points], axis=1),
    )
    known = [by_name[c.name].cam_from_world for c in result.cameras]
    for camera, pose in zip(result.cameras, known, strict=True):  # the background's static poses are held
        if pose is not None:
            camera.R, camera.t = np.asarray(pose[0], dtype=float), np.asarray(pose[1], dtype=float)
    reference = int(np.argmin(np.abs(offsets[:n])))  # the subject path's clock (its reference is at 0)
    centre = result.cameras[reference].centre
    finite = np.isfinite(knots.X[..., 0])
    bundle = Bundle(
        cams=list(range(len(obs))),
        rvec=np.array([rotation_vector(c.R) for c in result.cameras] + [np.zeros(3)] * len(anchors)),
        t=np.array([c.t for c in result.cameras] + [np.zeros(3)] * len(anchors)),
        focal=np.array([o.focal for o in obs]),
        k1=np.zeros(len(obs)),
        k2=np.zeros(len(obs)),
        pp=np.array([o.K[:2, 2] for o in obs]),
        offsets=offsets,
        knots=knots,
        fixed_pose=set(range(n, len(obs))) | {j for j, pose in enumerate(known) if pose is not None},
        fixed_offset={reference},
        gauge=None,
        keep=[_thinned(o) for o in obs],
        depth=float(np.median(np.linalg.norm(knots.X[finite] - centre, axis=-1))) if finite.any() else 1.0,
        frame_poses={n + i: (v.R, v.t) for i, v in enumerate(anchors)},
    )
    end = knots.t0 + (len(knots.X) - 1) * knots.h
    for i, video in enumerate(anchors):  # a phone filming longer than the static cameras: only the shared span
        clock = video.times + offsets[n + i]
        bundle.keep[n + i] &= ((clock >= knots.t0) & (clock <= end))[:, None]
    px = result.inlier_px
    limit = max_residual_px(px)
    adjust(bundle, obs, px, rounds=1)  # started near its optimum; the static videos' outliers are known
    bundle.knots.X[~supported(bundle, obs)] = np.nan
    errors = residuals_px(bundle, obs)
    bad = []
    for j, camera in enumerate(result.cameras):
        camera.R, camera.t = rotation(bundle.rvec[j]), bundle.t[j].copy()
        camera.offset = float(bundle.offsets[j])
        camera.inliers, camera.residual_px = _count(errors[j], px)
        if camera.residual_px > limit:
            bad.append(f"{camera.name}: {camera.residual_px:.1f} px from its own tracks")
        if known[j] is not None and any(f.name == camera.name for f in alignment.fits):
            fit = alignment.fit(camera.name)
            fit.offset, (fit.inliers, fit.residual_px) = camera.offset, _count(errors[j], px)
    for i, video in enumerate(anchors):
        fit = alignment.fit(video.name)
        fit.offset = float(bundle.offsets[n + i])
        fit.inliers, fit.residual_px = _count(errors[n + i], px)
        fit.observations = len(errors[n + i])
        if fit.residual_px > limit or fit.inliers < MIN_INLIERS:
            fit.reason = (
                f"the subject's trajectory reprojects {fit.residual_px:.1f} px from its tracks "
                f"({fit.inliers} of {fit.observations} within {3 * px:g} px)"
            )
            bad.append(f"{video.name}: {fit.reason}")
    if bad:
        raise SubjectCalibrationError(
            "the posed videos and the static videos' tracks disagree after adjusting them together: " + "; ".join(bad)
        )
    result.points = {p: bundle.knots.X[:, i].copy() for i, p in enumerate(points)}
    log.info(
        "adjusted with the posed videos: %s",
        ", ".join(f"{f.name} {f.residual_px:.2f} px" for f in alignment.fits if f.reason is None),
    )


def _posed_obs(video: PosedVideo, points: list[str]) -> VideoObs:
    """A posed video as bundle observations: normalized coordinates (known intrinsics) of `points`, on its posed
    frames."""
    posed = np.isfinite(video.R[:, 0, 0])
    norm = np.where(posed[:, None, None], video.columns(points), np.nan)
    focal = float(np.nanmedian(video.focal)) if np.isfinite(video.focal).any() else 1.0
    K = np.array([[focal, 0.0, 0.0], [0.0, focal, 0.0], [0.0, 0.0, 1.0]])
    return VideoObs(
        name=video.name,
        video=SubjectVideo(name=video.name, width=video.width, height=video.height, times=video.times, K=K),
        times=video.times,
        period=video.period,
        xy=norm * focal,  # pixels from the principal point: only which are seen matters to the bundle
        norm=norm,
        K=K,
        known_K=True,
        dist=None,
    )


def _count(errors: np.ndarray, px: float) -> tuple[int, float]:
    finite = errors[np.isfinite(errors)]
    return int((finite <= 3 * px).sum()), float(np.median(finite)) if len(finite) else float("inf")
