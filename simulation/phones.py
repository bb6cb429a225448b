"""Phone-like captures of a motion: free-running clocks, concurrent frames, handheld cameras.

Unlike the paper's protocol (`simulation.simulate`: static cameras, each mocap sample seen by exactly one
camera), every camera here records on its own:

- its own nominal frame rate `fps` (24-60 fps, non-integer ratios by default), its own start `offset_s` and an
  optional clock drift; captures of different cameras may coincide (no exclusivity);
- optional Gaussian frame-time jitter and handheld motion (a smooth stationary random sway of the centre and
  of the orientation; every frame has its own R, t);
- ground truth interpolated (cubic spline) from the mocap at each true capture time.

Clock model (scored by `clocks_truth.json`), for frame k of video v:

    own_time    = k / fps_v                                   (what cameras.json `time` holds, CFR timestamps)
    global_time = offset_s_v + rate_v * own_time + jitter_k    (the true capture time, truth.csv `time`)
    rate_v      = 1 + drift_v                                   (global seconds per own second)

Global time 0 is the first sample of the mocap window (simulated scenes: the start of the scene). With
`timestamps=Timestamps.VFR` the decoder time carries the jitter instead (own_time = k / fps + jitter_k / rate_v),
so global_time = offset_s_v + rate_v * own_time holds exactly. Captures whose true time falls outside the
mocap window or inside a gap of the mocap are dropped: their frame numbers are absent from cameras.json.

From Python:

    from reconstruct.outputs.mocap import read_mocap
    from simulation.phones import PhoneCaptureOptions, simulate_phones, run
    capture, record = simulate_phones(read_mocap(path), PhoneCaptureOptions(handheld=True, noise_px=1.0))
    capture.cameras, capture.tracks, capture.truth   # CameraSet, Tracks, FramePoints (extra "time", ...)
    record.clocks                                    # list[TrueClock]: name, fps, offset_s, rate, drift
    run(path, out_dir, options)                      # writes cameras.json, tracks.csv, truth.csv,
                                                     # clocks_truth.json, simulation.json

`capture_scene` is the mode-independent core (any `position(times) -> (N, P, 3)`); `simulation.flight` uses it.
"""

from __future__ import annotations

import enum
import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import DynreconError
from reconstruct.clocks.model import Clock
from reconstruct.outputs.mocap import Mocap, drop_incomplete, read_mocap, select_window
from reconstruct.outputs.points import FramePoints, write_points
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras
from simulation.simulate import (
    MIN_DEPTH_FRACTION,
    Rig,
    SimulatedCapture,
    SimulationOptions,
    clear_solve_outputs,
    place_cameras,
)
from tracking.tracks import Tracks, write_tracks

log = logging.getLogger(__name__)

# Common phone rates; every ratio among the first four is non-integer. Cycled when there are more cameras.
DEFAULT_FPS = (30.0, 25.0, 59.94, 24.0, 29.97, 50.0)
MAX_JITTER_FRAMES = 0.4  # jitter is clipped to this share of a frame period, so frames keep their order
KNOT_SPACING_S = 0.02  # the handheld motion is drawn on knots this far apart, then splined
GAP_SAMPLES = 1.5  # a capture between two mocap samples farther apart than this x the period is in a gap
MAX_FALSE_DRAWS = 1000  # rejection sampling of false detections far from the truth


class Timestamps(enum.Enum):
    """What cameras.json `time` holds (the decoder's presentation time, on the camera's own clock)."""

    CFR = "cfr"  # k / fps: a constant-frame-rate file; jitter is invisible
    VFR = "vfr"  # the real capture instant on the camera's clock: k / fps + jitter / rate


@dataclass(kw_only=True)
class CaptureOptions:
    """Clocks, handheld motion and detections: shared by the phone mode and the flight scene."""

    cameras: int = 4
    fps: tuple[float, ...] | None = None  # nominal rate of each camera; None = DEFAULT_FPS, cycled
    offset_s: tuple[float, float] = (0.0, 0.5)  # each camera's start (global time of frame 0) ~ U(min, max)
    drift_ppm: float = 0.0  # each clock's rate error ~ U(-drift_ppm, +drift_ppm) parts per million
    jitter_ms: float = 0.0  # std of the Gaussian capture-time jitter of each frame (clipped to 0.4 frame)
    timestamps: Timestamps = Timestamps.CFR
    handheld: bool = False
    shake_mm: float = 20.0  # std of each coordinate of the centre's excursion from its base position
    shake_deg: float = 1.0  # std of each component of the orientation's excursion (rotation vector)
    shake_s: float = 0.5  # correlation time of the handheld motion (velocity std = shake / shake_s)
    noise_px: float = 0.0  # std of the Gaussian noise on each pixel coordinate
    miss: float = 0.0  # share of the visible observations removed at random
    false_fraction: float = 0.0  # share of the kept detections replaced by a random pixel far from the truth
    false_min_px: float = 50.0  # a false detection is at least this far from the true projection
    seed: int = 0


@dataclass(kw_only=True)
class PhoneCaptureOptions(CaptureOptions):
    """Phones watching a mocap window. Cameras are placed as in the paper's protocol (then shaken if handheld)."""

    start: int = 0  # first mocap frame of the window
    length: int | None = None  # window length in mocap frames; None = to the end
    max_marker_missing: float = 0.1  # markers missing more often than this (in the window) are dropped
    image_size: int = 1000  # width = height, pixels (the paper's virtual camera)
    focal_px: float = 1000.0
    distance_factor: float = 2.0  # camera distance / motion scale, before any push back (see simulate.py)
    camera_distance_mm: float | None = None  # fixed distance to the centroid, mm (the paper averages 2700)


@dataclass(kw_only=True)
class TrueClock:
    """The true clock of one video: global_time = offset_s + rate * own_time (+ the frame's jitter), the affine
    `reconstruct.clocks.model.Clock` that the solve recovers."""

    name: str
    fps: float  # nominal frame rate, as cameras.json reports it
    offset_s: float  # global time of frame 0 (may be before the window: those frames are absent)
    rate: float  # global seconds per own second, 1 + drift
    drift: float  # dimensionless rate error (the clock model's quadratic drift term is 0 here)

    @property
    def clock(self) -> Clock:
        return Clock.affine(self.offset_s, self.rate)

    def global_time(self, own_time: np.ndarray) -> np.ndarray:
        return self.clock.global_time(own_time)

    def own_time(self, global_time: np.ndarray) -> np.ndarray:
        return self.clock.own_time(global_time)


@dataclass(kw_only=True)
class CaptureRecord:
    """What the simulation drew, for clocks_truth.json, simulation.json and the tests."""

    clocks: list[TrueClock]
    timestamps: Timestamps
    jitter_ms: float
    frames: dict[str, int]  # posed frames per video
    dropped: dict[str, int]  # captures dropped per video (outside the window or in a mocap gap)
    out_of_image: int  # observations outside their image (not in tracks.csv, observed = 0)
    false_detections: int
    centres: dict[str, np.ndarray]  # video -> (N, 3) camera centre of each posed frame
    rig: Rig | None = None  # base poses of the phone mode


def _check_capture_options(options: CaptureOptions) -> None:
    problems = []
    if options.cameras < 2:
        problems.append(f"cameras = {options.cameras}: the solver needs at least 2")
    if options.fps is not None:
        if len(options.fps) != options.cameras:
            problems.append(f"{len(options.fps)} frame rates for {options.cameras} cameras: give one per camera")
        if any(not (math.isfinite(f) and 1 <= f <= 1000) for f in options.fps):
            problems.append(f"fps {list(options.fps)}: every rate must be within 1..1000")
    low, high = options.offset_s
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        problems.append(f"offset range {low}..{high}: needs min <= max")
    if not (math.isfinite(options.drift_ppm) and 0 <= options.drift_ppm <= 1e5):
        problems.append(f"drift = {options.drift_ppm} ppm: must be within 0..100000")
    if not (math.isfinite(options.jitter_ms) and options.jitter_ms >= 0):
        problems.append(f"jitter = {options.jitter_ms} ms: must be >= 0")
    if options.handheld and not (options.shake_mm >= 0 and options.shake_deg >= 0 and options.shake_s > 0):
        problems.append("shake amplitudes must be >= 0 and the shake time > 0")
    if not (math.isfinite(options.noise_px) and options.noise_px >= 0):
        problems.append(f"noise = {options.noise_px}: must be >= 0 pixels")
    if not (0 <= options.miss < 1):
        problems.append(f"miss = {options.miss}: must be a fraction in [0, 1)")
    if not (0 <= options.false_fraction < 1):
        problems.append(f"false fraction = {options.false_fraction}: must be a fraction in [0, 1)")
    if not (math.isfinite(options.false_min_px) and options.false_min_px >= 0):
        problems.append(f"false detection distance = {options.false_min_px}: must be >= 0 pixels")
    if problems:
        raise DynreconError("invalid simulation options: " + "; ".join(problems))


# ------------------------------------------------------------------------------------------------------------
# Clocks


def draw_clocks(options: CaptureOptions, rng: np.random.Generator) -> list[TrueClock]:
    """One true clock per camera `cam0..`: nominal rate, start offset and drift."""
    rates = (
        options.fps
        if options.fps is not None
        else tuple(DEFAULT_FPS[c % len(DEFAULT_FPS)] for c in range(options.cameras))
    )
    offsets = rng.uniform(options.offset_s[0], options.offset_s[1], size=options.cameras)
    drifts = rng.uniform(-1.0, 1.0, size=options.cameras) * options.drift_ppm * 1e-6
    return [
        TrueClock(
            name=f"cam{c}",
            fps=float(rates[c]),
            offset_s=float(offsets[c]),
            rate=1.0 + float(drifts[c]),
            drift=float(drifts[c]),
        )
        for c in range(options.cameras)
    ]


def capture_times(
    clock: TrueClock, span: tuple[float, float], jitter_s: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers (N,) whose nominal time lies in `span` (global s) and their true capture times (N,).

    The jitter is drawn for every frame and clipped to MAX_JITTER_FRAMES of a period; a jittered time may
    leave the span (the caller drops it).
    """
    period = clock.rate / clock.fps  # global seconds per frame
    first = max(0, math.ceil((span[0] - clock.offset_s) / period - 1e-9))
    last = math.floor((span[1] - clock.offset_s) / period + 1e-9)
    frames = np.arange(first, last + 1, dtype=np.int64)
    times = clock.global_time(frames / clock.fps)
    if jitter_s > 0 and len(frames):
        limit = MAX_JITTER_FRAMES * period
        times = times + np.clip(rng.normal(0.0, jitter_s, size=len(frames)), -limit, limit)
    return frames, times


# ------------------------------------------------------------------------------------------------------------
# Handheld motion


def smooth_walk(times: np.ndarray, dims: int, std: float, correlation_s: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth, stationary random motion at `times` (N,): (N, dims), each coordinate N(0, std^2).

    White noise on knots every KNOT_SPACING_S, Gaussian-filtered so that the covariance is
    std^2 exp(-dt^2 / (2 correlation_s^2)) (velocity std = std / correlation_s), then splined. Unlike a plain
    random walk it never drifts away, and unlike per-frame noise it is smooth: a hand swaying a phone.
    """
    times = np.asarray(times, dtype=float)
    if len(times) == 0 or std == 0:
        return np.zeros((len(times), dims))
    sigma = correlation_s / math.sqrt(2) / KNOT_SPACING_S  # kernel width in knots
    margin = 4 * sigma * KNOT_SPACING_S + KNOT_SPACING_S  # no edge effects inside the span
    t0, t1 = float(times.min()) - margin, float(times.max()) + margin
    count = max(4, math.ceil((t1 - t0) / KNOT_SPACING_S) + 1)
    knots_t = t0 + KNOT_SPACING_S * np.arange(count)
    white = rng.normal(0.0, 1.0, (count, dims))
    # A unit-sum Gaussian kernel of width sigma leaves 1 / (2 sqrt(pi) sigma) of white noise's variance.
    smooth = gaussian_filter1d(white, sigma, axis=0, mode="wrap") * math.sqrt(2 * math.sqrt(math.pi) * sigma)
    return np.asarray(CubicSpline(knots_t, std * smooth, axis=0)(times))


def handheld_poses(
    R: np.ndarray,
    t: np.ndarray,
    times: np.ndarray,
    options: CaptureOptions,
    rng: np.random.Generator,
    scale_mm: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world of each frame (N, 3, 3), (N, 3): a base pose (3, 3), (3,) shaken at the true `times` (N,).

    The orientation excursion is a rotation about the camera's own axes; the centre moves by `shake_mm` x
    `scale_mm` world units per coordinate (scale_mm = 1 for mm worlds).
    """
    count = len(times)
    if not options.handheld:
        return np.repeat(R[None], count, axis=0), np.repeat(t[None], count, axis=0)
    centre = -R.T @ t
    moves = smooth_walk(times, 3, options.shake_mm * scale_mm, options.shake_s, rng)
    turns = smooth_walk(times, 3, math.radians(options.shake_deg), options.shake_s, rng)
    Rs = Rotation.from_rotvec(turns).as_matrix() @ R  # (N, 3, 3)
    centres = centre + moves
    ts = -np.einsum("nij,nj->ni", Rs, centres)
    return Rs, ts


# ------------------------------------------------------------------------------------------------------------
# Detections


def _project(points: np.ndarray, K: np.ndarray, Rs: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, P, 2) and depths (N, P) of points (N, P, 3) seen by per-frame cameras (N, 3, 3), (N, 3)."""
    cam = np.einsum("nij,npj->npi", Rs, points) + ts[:, None, :]
    depth = cam[..., 2]
    uv = cam[..., :2] / depth[..., None] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, depth


def detect(
    uv: np.ndarray, inside: np.ndarray, size: tuple[int, int], options: CaptureOptions, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Detections of true projections `uv (N, P, 2)`; `inside (N, P)` = in the image.

    Returns pixels (N, P, 2), observed (N, P) (in tracks.csv) and false (N, P) (a random pixel at least
    `false_min_px` from the truth, uniform in the image). Noise on every coordinate; `miss` removes exactly
    round(miss x visible) observations; `false_fraction` replaces round(fraction x kept) of the rest.
    """
    xy = uv + rng.normal(0.0, options.noise_px, size=uv.shape) if options.noise_px > 0 else uv.copy()
    observed = inside.copy()
    visible = np.flatnonzero(observed.reshape(-1))
    removed = round(options.miss * len(visible))
    if removed:
        observed.reshape(-1)[rng.choice(visible, size=removed, replace=False)] = False
    false = np.zeros_like(observed)
    kept = np.flatnonzero(observed.reshape(-1))
    count = round(options.false_fraction * len(kept))
    if count:
        width, height = size
        chosen = rng.choice(kept, size=count, replace=False)
        flat_xy = xy.reshape(-1, 2)
        flat_uv = uv.reshape(-1, 2)
        for index in chosen:
            for _ in range(MAX_FALSE_DRAWS):
                candidate = rng.uniform([-0.5, -0.5], [width - 0.5, height - 0.5])
                if np.linalg.norm(candidate - flat_uv[index]) >= options.false_min_px:
                    break
            else:
                raise DynreconError(
                    f"cannot place a false detection {options.false_min_px} px from the truth in a "
                    f"{width} x {height} image: use a smaller distance"
                )
            flat_xy[index] = candidate
        false.reshape(-1)[chosen] = True
    return xy, observed, false


# ------------------------------------------------------------------------------------------------------------
# The core: any scene, any cameras


@dataclass(kw_only=True)
class _CameraShots:
    """What one camera recorded: its posed frames and the true projections of every point at each."""

    video: VideoCameras
    dropped: int  # captures outside the window or in a gap of the truth
    frames: np.ndarray  # (N,) frame numbers
    times: np.ndarray  # (N,) true global capture times
    xyz: np.ndarray  # (N, P, 3) true points
    uv: np.ndarray  # (N, P, 2) true projections
    inside: np.ndarray  # (N, P) projection inside the image
    centres: np.ndarray  # (N, 3) camera centre of each frame


def _shoot_camera(
    clock: TrueClock,
    R: np.ndarray,
    t: np.ndarray,
    position: Callable[[np.ndarray], np.ndarray],
    valid: Callable[[np.ndarray], np.ndarray],
    span: tuple[float, float],
    point_count: int,
    K: np.ndarray,
    size: tuple[int, int],
    options: CaptureOptions,
    rng: np.random.Generator,
    min_depth: float,
    world_per_mm: float,
) -> _CameraShots:
    """One camera's frames inside `span`, posed (and shaken) at their true times, and the true projections."""
    width, height = size
    frames, times = capture_times(clock, span, options.jitter_ms / 1000.0, rng)
    keep = (times >= span[0]) & (times <= span[1])
    keep[keep] = valid(times[keep])
    dropped = int((~keep).sum())
    frames, times = frames[keep], times[keep]
    if len(frames) < 2:
        log.warning("camera %s has %d frame(s) inside the window", clock.name, len(frames))
    Rs, ts = handheld_poses(R, t, times, options, rng, scale_mm=world_per_mm)
    points = position(times) if len(times) else np.zeros((0, point_count, 3))
    uv, depth = _project(points, K, Rs, ts)
    if depth.size and depth.min() < min_depth:
        raise DynreconError(
            f"camera {clock.name} comes within {max(float(depth.min()), 0.0):.0f} units of a point (or has it "
            "behind): use a larger camera distance or less handheld shake"
        )
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= width - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= height - 0.5)
    # VFR: the capture instant on the camera's own clock; CFR: the nominal frame time.
    own = clock.own_time(times) if options.timestamps is Timestamps.VFR else frames / clock.fps
    video = VideoCameras(
        name=clock.name,
        width=width,
        height=height,
        fps=clock.fps,
        frames=[
            FrameCamera(frame=int(f), K=K.copy(), R=Rs[i].copy(), t=ts[i].copy(), time=float(own[i]))
            for i, f in enumerate(frames)
        ],
    )
    return _CameraShots(
        video=video,
        dropped=dropped,
        frames=frames,
        times=times,
        xyz=points,
        uv=uv,
        inside=inside,
        centres=-np.einsum("nji,nj->ni", Rs, ts),
    )


def _detect_shots(
    shots: list[_CameraShots],
    point_names: list[str],
    size: tuple[int, int],
    options: CaptureOptions,
    rng: np.random.Generator,
) -> tuple[FramePoints, Tracks, np.ndarray, np.ndarray]:
    """Truth and tracks of every camera's frames (rows grouped by video then frame); also inside and false (F, P)."""
    P = len(point_names)
    names = [shot.video.name for shot in shots for _ in range(len(shot.frames))]
    xyz = np.concatenate([shot.xyz for shot in shots])  # (F, P, 3)
    uv = np.concatenate([shot.uv for shot in shots])
    inside = np.concatenate([shot.inside for shot in shots])
    frame_of = np.concatenate([shot.frames for shot in shots])
    time_of = np.concatenate([shot.times for shot in shots])
    if len(frame_of) == 0:
        raise DynreconError(
            "no camera captured a frame inside the window: use smaller start offsets or a longer window"
        )
    xy, observed, false = detect(uv, inside, size, options, rng)
    truth = FramePoints(
        videos=names,
        frames=frame_of,
        point_names=list(point_names),
        xyz=xyz,
        observed=observed,
        extra={"time": np.repeat(time_of[:, None], P, axis=1), "false_detection": false.astype(float)},
    )
    seen_frame, seen_point = np.nonzero(observed)
    tracks = Tracks(
        video=[names[i] for i in seen_frame],
        frame=frame_of[seen_frame],
        point=[point_names[p] for p in seen_point],
        xy=xy[seen_frame, seen_point],
    )
    return truth, tracks, inside, false


def capture_scene(
    position: Callable[[np.ndarray], np.ndarray],
    valid: Callable[[np.ndarray], np.ndarray],
    span: tuple[float, float],
    point_names: list[str],
    K: np.ndarray,
    base_R: np.ndarray,
    base_t: np.ndarray,
    size: tuple[int, int],
    options: CaptureOptions,
    rng: np.random.Generator,
    *,
    min_depth: float,
    world_per_mm: float = 1.0,
) -> tuple[SimulatedCapture, CaptureRecord]:
    """Every camera records the scene on its own clock.

    position(times (N,)) -> (N, P, 3) world points at global times; valid(times) -> (N,) bool (False: no
    truth there, the capture is dropped). base_R (C, 3, 3), base_t (C, 3): cam_from_world before shaking.
    size = (width, height) px. A true point closer than `min_depth` to a camera (or behind it) is an error.
    """
    _check_capture_options(options)
    clocks = draw_clocks(options, rng)
    # One camera at a time, in clock order: the random draws keep the order of the seeded runs.
    shots = [
        _shoot_camera(
            clock,
            base_R[c],
            base_t[c],
            position,
            valid,
            span,
            len(point_names),
            K,
            size,
            options,
            rng,
            min_depth,
            world_per_mm,
        )
        for c, clock in enumerate(clocks)
    ]
    truth, tracks, inside, false = _detect_shots(shots, point_names, size, options, rng)
    record = CaptureRecord(
        clocks=clocks,
        timestamps=options.timestamps,
        jitter_ms=options.jitter_ms,
        frames={clock.name: len(shot.frames) for clock, shot in zip(clocks, shots, strict=True)},
        dropped={clock.name: shot.dropped for clock, shot in zip(clocks, shots, strict=True)},
        out_of_image=int((~inside).sum()),
        false_detections=int(false.sum()),
        centres={clock.name: shot.centres for clock, shot in zip(clocks, shots, strict=True)},
    )
    if record.out_of_image:
        log.info(
            "%d of %d true projections fall outside their image: left out of tracks.csv",
            record.out_of_image,
            inside.size,
        )
    log.info(
        "captured %d frames of %d points in %d cameras: %d observations (%d false)",
        len(truth.frames),
        len(point_names),
        len(clocks),
        len(tracks),
        record.false_detections,
    )
    return SimulatedCapture(
        cameras=CameraSet(videos=[shot.video for shot in shots]), tracks=tracks, truth=truth
    ), record


# ------------------------------------------------------------------------------------------------------------
# Phones watching a mocap window


def mocap_truth(window: Mocap) -> tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]:
    """Cubic-spline positions of a complete window at global times (0 = its first sample), and where they hold.

    A time is valid inside the window and between two samples that are neighbours in the file (a frame the
    cleaning dropped leaves a gap; captures inside it have no truth).
    """
    times = window.times - window.times[0]
    T, M = window.xyz.shape[:2]
    if T < 2:
        raise DynreconError("the mocap window has fewer than 2 complete frames: choose a longer window")
    spline = CubicSpline(times, window.xyz.reshape(T, M * 3), axis=0)
    max_gap = GAP_SAMPLES / window.rate

    def position(t: np.ndarray) -> np.ndarray:
        return np.asarray(spline(t)).reshape(len(t), M, 3)

    def valid(t: np.ndarray) -> np.ndarray:
        after = np.clip(np.searchsorted(times, t, side="left"), 1, T - 1)
        return (t >= times[0]) & (t <= times[-1]) & (times[after] - times[after - 1] <= max_gap)

    return position, valid


def simulate_phones(mocap: Mocap, options: PhoneCaptureOptions | None = None) -> tuple[SimulatedCapture, CaptureRecord]:
    """Window and clean `mocap` (mm), place the cameras as the paper does, and let each phone record it."""
    options = options or PhoneCaptureOptions()
    _check_capture_options(options)
    window = select_window(mocap, start=options.start, length=options.length)
    window = drop_incomplete(window, max_missing=options.max_marker_missing, whole=mocap)
    position, valid = mocap_truth(window)
    rng = np.random.default_rng(options.seed)
    rig = place_cameras(
        window.xyz,
        SimulationOptions(
            cameras=options.cameras,
            image_size=options.image_size,
            focal_px=options.focal_px,
            distance_factor=options.distance_factor,
            camera_distance_mm=options.camera_distance_mm,
        ),
        rng,
    )
    span = (0.0, float(window.times[-1] - window.times[0]))
    capture, record = capture_scene(
        position,
        valid,
        span,
        list(window.marker_names),
        rig.K,
        rig.R,
        rig.t,
        (options.image_size, options.image_size),
        options,
        rng,
        min_depth=MIN_DEPTH_FRACTION * rig.distance,
    )
    record.rig = rig
    return capture, record


# ------------------------------------------------------------------------------------------------------------
# Files


def clocks_document(record: CaptureRecord, time_origin: str) -> dict[str, Any]:
    """The content of clocks_truth.json."""
    return {
        "model": "global_time = offset_s + rate * own_time + jitter; own_time = cameras.json time",
        "time_origin": time_origin,
        "timestamps": record.timestamps.value,
        "jitter_ms": record.jitter_ms,
        "videos": [
            {
                "name": c.name,
                "fps": c.fps,
                "offset_s": c.offset_s,
                "rate": c.rate,
                "drift": c.drift,
                "drift_ppm": c.drift * 1e6,
                "frames": record.frames[c.name],
            }
            for c in record.clocks
        ],
    }


def options_record(options: CaptureOptions) -> dict[str, Any]:
    """asdict with enums as their values (JSON-ready)."""
    return {k: v.value if isinstance(v, enum.Enum) else v for k, v in asdict(options).items()}


def write_capture(
    out: Path, capture: SimulatedCapture, record: CaptureRecord, simulation: dict[str, Any], time_origin: str
) -> Path:
    """cameras.json, tracks.csv, truth.csv, clocks_truth.json and simulation.json into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    clear_solve_outputs(out)
    write_cameras(out / "cameras.json", capture.cameras)
    write_tracks(out / "tracks.csv", capture.tracks)
    write_points(out / "truth.csv", capture.truth)
    atomic_write_text(out / "clocks_truth.json", json.dumps(clocks_document(record, time_origin), indent=1) + "\n")
    simulation = {
        **simulation,
        "captures": capture.truth.num_frames,
        "points": capture.truth.point_names,
        "observations": len(capture.tracks),
        "frames_per_video": record.frames,
        "dropped_per_video": record.dropped,
        "out_of_image": record.out_of_image,
        "false_detections": record.false_detections,
    }
    atomic_write_text(out / "simulation.json", json.dumps(simulation, indent=1) + "\n")
    return out


def run(mocap_path: str | Path, out_dir: str | Path, options: PhoneCaptureOptions | None = None) -> Path:
    """Simulate phones watching a mocap file into `out_dir` (see write_capture); returns out_dir."""
    options = options or PhoneCaptureOptions()
    mocap = read_mocap(mocap_path)
    capture, record = simulate_phones(mocap, options)
    rig = record.rig
    assert rig is not None  # simulate_phones always sets it
    simulation = {
        "mode": "phones",
        "mocap": str(mocap_path),
        "rate_hz": mocap.rate,
        "options": options_record(options),
        "centroid_mm": rig.centroid.tolist(),
        "up": rig.up.tolist(),
        "scale_mm": rig.scale,
        "camera_distance_mm": rig.distance,
    }
    return write_capture(Path(out_dir), capture, record, simulation, time_origin="the first sample of the mocap window")
