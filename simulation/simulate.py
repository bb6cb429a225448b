"""The seed paper's simulation protocol: project real motion capture into static virtual cameras.

Each capture time (one mocap sample) is seen by exactly one camera, chosen at random; by default no camera
takes two consecutive captures. Cameras are 1000 x 1000 px, f = 1000, principal point at the image centre
(OpenCV: 499.5), placed evenly in azimuth at the height of the motion's centroid, looking at it, at
`distance_factor` times the motion's scale (the largest distance of any sample from the centroid), then moved
back until every sample of every frame projects inside every image. With a fixed distance (`camera_distance_mm`)
the cameras stay there and, where the motion projects outside 1000 px, the virtual images grow to hold it (the
paper's cameras have no frame edge; cameras.json then declares the larger size). Outputs are in mm, like the mocap.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import DynreconError, InputError
from reconstruct.outputs.mocap import Mocap, drop_incomplete, read_mocap, select_window
from reconstruct.outputs.points import FramePoints, write_points
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras
from tracking.tracks import Tracks, write_tracks

log = logging.getLogger(__name__)

MIN_DEPTH_FRACTION = 0.02  # with a fixed distance, no sample may come closer to a camera than this x distance
IMAGE_MARGIN_PX = 5.0  # every noise-free projection stays this far inside the image border
PUSH_BACK = 1.05  # distance growth per attempt while some point falls outside an image


@dataclass(kw_only=True)
class SimulationOptions:
    cameras: int = 4
    step: int = 1  # keep every step-th mocap sample: 120 Hz / step overall, 120 / (step * cameras) per camera
    noise_px: float = 0.0  # standard deviation of the Gaussian noise on each pixel coordinate
    miss: float = 0.0  # fraction of the observations removed at random (exactly round(miss * T * M) of them)
    unconstrained: bool = False  # allow a camera to take two consecutive captures
    # Each frame's capture time in cameras.json; False: neither times nor fps, the paper's protocol as published.
    times: bool = True
    seed: int = 0
    start: int = 0  # first mocap frame of the window
    length: int | None = None  # window length in mocap frames (before `step`); None = to the end
    max_marker_missing: float = 0.1  # markers missing more often than this (in the window) are dropped
    image_size: int = 1000  # width = height, pixels
    focal_px: float = 1000.0
    distance_factor: float = 2.0  # camera distance to the centroid / motion scale (before any push back)
    # Fixed camera distance in mm (the paper's protocol averages 2.7 m): no push back, so points of a motion that
    # travels far may project outside the virtual 1000 x 1000 image; the solver does not mind.
    camera_distance_mm: float | None = None


class SimulatedCapture(NamedTuple):
    cameras: CameraSet  # videos cam0..cam{C-1}, one posed frame per capture
    tracks: Tracks  # observed projections only
    truth: FramePoints  # every posed frame and marker, mm, `observed` as simulated, extra "time" (s)


@dataclass(kw_only=True)
class Rig:
    """Where the cameras were put, for the record and the tests."""

    centroid: np.ndarray  # (3,) mm
    up: np.ndarray  # (3,) unit vector of the vertical axis
    scale: float  # mm, the largest distance of any sample from the centroid
    distance: float  # mm, camera centre to centroid (all cameras)
    R: np.ndarray  # (C, 3, 3) cam_from_world
    t: np.ndarray  # (C, 3)
    K: np.ndarray  # (3, 3)
    image_size: int  # px, width = height: the option's size, or larger where a fixed distance needs it


def _check_options(options: SimulationOptions) -> None:
    problems = []
    if options.cameras < 2:
        problems.append(f"cameras = {options.cameras}: the solver needs at least 2")
    if options.step < 1:
        problems.append(f"step = {options.step}: must be >= 1")
    if not (math.isfinite(options.noise_px) and options.noise_px >= 0):
        problems.append(f"noise = {options.noise_px}: must be >= 0 pixels")
    if not (0 <= options.miss < 1):
        problems.append(f"miss = {options.miss}: must be a fraction in [0, 1)")
    if options.image_size < 2 or not options.focal_px > 0 or not options.distance_factor > 0:
        problems.append("image size, focal length and distance factor must be positive")
    if problems:
        raise DynreconError("invalid simulation options: " + "; ".join(problems))


def vertical_axis(xyz: np.ndarray) -> np.ndarray:
    """The world axis along which one frame of a standing/moving body is tallest (median over frames), (3,).

    Mocap files use either Y up (OpenSim TRC) or Z up (Vicon C3D); the body's height is its longest extent in
    almost every frame, even while walking or running, so this finds the axis without a per-file setting.
    """
    extent = np.nanmax(xyz, axis=1) - np.nanmin(xyz, axis=1)  # (T, 3)
    axis = int(np.argmax(np.nanmedian(extent, axis=0)))
    up = np.zeros(3)
    up[axis] = 1.0
    return up


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at `center` looking at `target`, image y pointing down (OpenCV)."""
    z = target - center
    z = z / np.linalg.norm(z)
    y = -(up - (up @ z) * z)
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    return R, -R @ center


def project(points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (..., 2) and depths (...) of world points (..., 3)."""
    cam = points @ R.T + t
    depth = cam[..., 2]
    uv = cam[..., :2] / depth[..., None] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, depth


def place_cameras(xyz: np.ndarray, options: SimulationOptions, rng: np.random.Generator) -> Rig:
    """Cameras evenly spread in azimuth (random phase) around the centroid of all samples `xyz (T, M, 3)`."""
    samples = xyz.reshape(-1, 3)
    samples = samples[np.isfinite(samples).all(axis=1)]
    centroid = samples.mean(axis=0)
    up = vertical_axis(xyz)
    scale = float(np.linalg.norm(samples - centroid, axis=1).max())
    if scale <= 0:
        raise DynreconError("the motion has no extent: every marker sample is at the same place")
    size = options.image_size
    K = _intrinsics(options.focal_px, size)
    # Two horizontal directions orthogonal to `up`.
    h1 = np.roll(up, 1)
    h2 = np.cross(up, h1)
    phase = rng.uniform(0, 2 * np.pi / options.cameras)
    azimuths = phase + 2 * np.pi * np.arange(options.cameras) / options.cameras
    directions = np.cos(azimuths)[:, None] * h1 + np.sin(azimuths)[:, None] * h2  # (C, 3)
    if options.camera_distance_mm is not None:
        distance = options.camera_distance_mm
        poses = [look_at(centroid + distance * d, centroid, up) for d in directions]
        size = _fixed_distance_size(samples, K, poses, distance, scale, size)
        K = _intrinsics(options.focal_px, size)
    else:
        distance = options.distance_factor * scale
        for _ in range(200):
            poses = [look_at(centroid + distance * d, centroid, up) for d in directions]
            if all(_inside(samples, K, R, t, size) for R, t in poses):
                break
            distance *= PUSH_BACK
        else:  # pragma: no cover - 1.05^200 is far beyond any finite motion
            raise DynreconError("could not place the cameras so that every point is inside the images")
        if distance > options.distance_factor * scale * 1.001:
            log.info(
                "cameras moved back to %.0f mm (%.2f x the motion scale) to keep every point in the images",
                distance,
                distance / scale,
            )
    return Rig(
        centroid=centroid,
        up=up,
        scale=scale,
        distance=distance,
        K=K,
        image_size=size,
        R=np.stack([p[0] for p in poses]),
        t=np.stack([p[1] for p in poses]),
    )


def _intrinsics(focal_px: float, size: int) -> np.ndarray:
    """(3, 3) K of a size x size image with its principal point at the centre (OpenCV: top-left pixel at 0)."""
    centre_px = (size - 1) / 2.0
    return np.array([[focal_px, 0, centre_px], [0, focal_px, centre_px], [0, 0, 1.0]])


def _inside(samples: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, size: int) -> bool:
    uv, depth = project(samples, K, R, t)
    return bool((depth > 0).all() and (uv >= IMAGE_MARGIN_PX).all() and (uv <= size - 1 - IMAGE_MARGIN_PX).all())


def _fixed_distance_size(
    samples: np.ndarray,
    K: np.ndarray,
    poses: list[tuple[np.ndarray, np.ndarray]],
    distance: float,
    scale: float,
    size: int,
) -> int:
    """The image size at a fixed camera distance: `size`, or larger where the motion projects outside it. The
    paper's virtual cameras have no frame edge, so every projection is kept and cameras.json declares an image that
    holds it (else they would be observations outside the image)."""
    centre_px = float(K[0, 2])
    reach = 0.0  # px, the farthest projection from the principal point along either image axis
    for k, (R, t) in enumerate(poses):
        uv, depth = project(samples, K, R, t)
        if depth.min() < MIN_DEPTH_FRACTION * distance:
            raise DynreconError(
                f"--distance {distance:.0f} mm puts the motion within {max(depth.min(), 0):.0f} mm of camera "
                f"{k} (or behind it): the motion spans {2 * scale:.0f} mm; use a larger distance or a shorter window"
            )
        reach = max(reach, float(np.abs(uv - centre_px).max()))
    if reach <= centre_px + 0.5:  # inside the image (perhaps within its margin): nothing to grow
        return size
    grown = math.ceil(2 * (reach + IMAGE_MARGIN_PX)) + 1
    log.info(
        "at %.0f mm the motion reaches %.0f px from the image centre: virtual images of %d px", distance, reach, grown
    )
    return grown


def assign_cameras(count: int, cameras: int, unconstrained: bool, rng: np.random.Generator) -> np.ndarray:
    """Camera of each of `count` captures, (count,); consecutive captures differ unless unconstrained."""
    if unconstrained:
        return rng.integers(cameras, size=count)
    assignment = np.empty(count, dtype=np.int64)
    if count == 0:
        return assignment
    assignment[0] = rng.integers(cameras)
    draws = rng.integers(cameras - 1, size=count)
    for k in range(1, count):
        # Uniform among the other cameras: skip over the previous one.
        assignment[k] = draws[k] + (draws[k] >= assignment[k - 1])
    return assignment


def _observe(
    xyz: np.ndarray, assignment: np.ndarray, rig: Rig, options: SimulationOptions, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy pixels (T, M, 2) of each capture in its camera, and observed (T, M) after the random misses."""
    T, M = xyz.shape[:2]
    uv = np.empty((T, M, 2))
    for c in range(options.cameras):
        chosen = assignment == c
        uv[chosen] = project(xyz[chosen], rig.K, rig.R[c], rig.t[c])[0]
    if options.noise_px > 0:
        uv += rng.normal(0.0, options.noise_px, size=uv.shape)
    observed = np.ones((T, M), dtype=bool)
    removed = round(options.miss * T * M)
    if removed:
        observed.reshape(-1)[rng.choice(T * M, size=removed, replace=False)] = False
    return uv, observed


def _video_cameras(
    assignment: np.ndarray, times: np.ndarray, rig: Rig, options: SimulationOptions
) -> tuple[list[VideoCameras], np.ndarray, np.ndarray]:
    """Each camera's video, the frame number of each capture inside its video, and the captures grouped by
    video then in time order (= frame order)."""
    T = len(assignment)
    frame_of = np.empty(T, dtype=np.int64)
    videos = []
    order: list[int] = []
    for c in range(options.cameras):
        captures = np.flatnonzero(assignment == c)
        frame_of[captures] = np.arange(len(captures))
        order.extend(captures.tolist())
        if len(captures) == 0:
            log.warning("camera cam%d got no capture (only %d captures)", c, T)
        videos.append(
            VideoCameras(
                name=f"cam{c}",
                width=rig.image_size,
                height=rig.image_size,
                # Captures are assigned at random, so frame / fps is not a capture time: leave fps unknown and
                # give each frame its `time`.
                fps=None,
                frames=[
                    FrameCamera(
                        frame=int(frame_of[k]),
                        K=rig.K.copy(),
                        R=rig.R[c].copy(),
                        t=rig.t[c].copy(),
                        time=float(times[k]) if options.times else None,
                    )
                    for k in captures
                ],
            )
        )
    return videos, frame_of, np.array(order, dtype=np.int64)


def simulate_mocap(mocap: Mocap, options: SimulationOptions) -> tuple[SimulatedCapture, Rig]:
    """Window, clean and simulate one capture; returns the capture and where the cameras were."""
    _check_options(options)
    window = select_window(mocap, start=options.start, length=options.length, step=options.step)
    window = drop_incomplete(window, max_missing=options.max_marker_missing, whole=mocap)
    xyz = window.xyz  # (T, M, 3) complete
    T, M = xyz.shape[:2]
    rng = np.random.default_rng(options.seed)
    rig = place_cameras(xyz, options, rng)
    assignment = assign_cameras(T, options.cameras, options.unconstrained, rng)
    if len(set(assignment.tolist())) < 2:  # the solve needs two videos: refused here, where the cause is known
        raise InputError(
            mocap.path,
            f"{T} capture{'s' if T != 1 else ''} to simulate (after the window and the cleaning): at least two "
            "cameras must each film one",
            fix="give a trial with more frames (or a longer --length)"
            + (
                ", or leave out --unconstrained (its draw gave every capture to one camera)"
                if options.unconstrained
                else ""
            ),
        )
    uv, observed = _observe(xyz, assignment, rig, options, rng)

    # Every virtual camera starts recording at the first capture; rounding hides the float noise of the
    # subtraction (the file's clock can start at an arbitrary offset).
    times = np.round(window.times - window.times[0], 12)
    videos, frame_of, rows = _video_cameras(assignment, times, rig, options)
    names = [f"cam{c}" for c in assignment[rows]]
    truth = FramePoints(
        videos=names,
        frames=frame_of[rows],
        point_names=list(window.marker_names),
        xyz=xyz[rows].copy(),
        observed=observed[rows].copy(),
        extra={"time": np.repeat(times[rows, None], M, axis=1)},
    )
    seen_capture, seen_marker = np.nonzero(observed[rows])
    tracks = Tracks(
        video=[names[i] for i in seen_capture],
        frame=frame_of[rows][seen_capture],
        point=[window.marker_names[p] for p in seen_marker],
        xy=uv[rows][seen_capture, seen_marker],
    )
    log.info(
        "simulated %d captures x %d markers into %d cameras at %.0f mm (scale %.0f mm): %d observations",
        T,
        M,
        options.cameras,
        rig.distance,
        rig.scale,
        len(tracks),
    )
    return SimulatedCapture(cameras=CameraSet(videos=videos), tracks=tracks, truth=truth), rig


def simulate_capture(
    xyz: np.ndarray, rate: float, options: SimulationOptions | None = None, *, marker_names: list[str] | None = None
) -> SimulatedCapture:
    """In-memory simulation of `xyz (T, M, 3)` mm sampled at `rate` Hz (NaN = missing sample)."""
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or xyz.shape[0] == 0 or xyz.shape[1] == 0:
        raise DynreconError(f"xyz must have shape (T, M, 3) with T, M > 0, got {xyz.shape}")
    names = marker_names if marker_names is not None else [f"p{i}" for i in range(xyz.shape[1])]
    mocap = Mocap(xyz=xyz, rate=float(rate), marker_names=list(names), times=np.arange(xyz.shape[0]) / rate)
    return simulate_mocap(mocap, options or SimulationOptions())[0]


# A solve's files in a simulation folder: made from the capture that a new simulation replaces
SOLVE_OUTPUTS = ("points3d.csv", "sequencing.json", "report.json", "recording.rrd")


def clear_solve_outputs(out: Path) -> None:
    """Remove an earlier solve's files from `out` (`evaluate` would score them against the new truth), saying so."""
    removed = [name for name in SOLVE_OUTPUTS if (out / name).is_file()]
    for name in removed:
        (out / name).unlink()
    if removed:
        log.warning(
            "%s: removed %s of an earlier solve (of the capture this simulation replaces)", out, ", ".join(removed)
        )


def run(mocap_path: str | Path, out_dir: str | Path, options: SimulationOptions | None = None) -> Path:
    """Simulate from a mocap file into `out_dir`: cameras.json, tracks.csv, truth.csv, simulation.json."""
    options = options or SimulationOptions()
    out = Path(out_dir)
    mocap = read_mocap(mocap_path)
    capture, rig = simulate_mocap(mocap, options)
    out.mkdir(parents=True, exist_ok=True)
    clear_solve_outputs(out)
    write_cameras(out / "cameras.json", capture.cameras)
    write_tracks(out / "tracks.csv", capture.tracks)
    write_points(out / "truth.csv", capture.truth)
    record = {
        "mocap": str(mocap_path),
        "rate_hz": mocap.rate,
        "capture_rate_hz": mocap.rate / options.step,
        "options": asdict(options),
        "captures": capture.truth.num_frames,
        "points": capture.truth.point_names,
        "observations": len(capture.tracks),
        "centroid_mm": rig.centroid.tolist(),
        "up": rig.up.tolist(),
        "scale_mm": rig.scale,
        "camera_distance_mm": rig.distance,
        "image_size_px": rig.image_size,
    }
    atomic_write_text(out / "simulation.json", json.dumps(record, indent=1) + "\n")
    return out
