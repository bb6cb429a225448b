"""A single moving point seen from far away: a drone on a smooth 3D flight path, filmed by 4-5 phones.

The scene for clock recovery and robustness: one point (`drone`) on a sum of sinusoids per axis (tens of
metres, drone speeds), cameras 30-100 m away on the ground at their own rates and start offsets
(`simulation.phones`'s clocks and handheld motion), 1-2 px detection noise and a few per cent of false
detections far from the truth, uniform in the image. Units: millimetres, like every other simulation (so
`dynrecon evaluate`'s 10..100 thresholds are mm); world Z up, origin on the ground below the path's centre.

From Python:

    from simulation.flight import FlightOptions, simulate_flight, run
    capture, record, scene = simulate_flight(FlightOptions(seed=1))
    run(out_dir, FlightOptions(duration_s=10.0))   # the files of simulation.phones.write_capture
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynrecon.errors import DynreconError
from simulation.phones import CaptureOptions, CaptureRecord, capture_scene, options_record, write_capture
from simulation.simulate import SimulatedCapture, look_at

MM_PER_M = 1000.0
COMPONENTS = 3  # sinusoids per axis
SPEED_ITERATIONS = 6  # fixed-point rescaling of the frequencies to the requested mean speed
MIN_DEPTH_MM = 1000.0
UP = np.array([0.0, 0.0, 1.0])


@dataclass(kw_only=True)
class FlightOptions(CaptureOptions):
    """The scene; capture fields (clocks, handheld, detections) as in CaptureOptions, with flight defaults."""

    cameras: int = 5
    offset_s: tuple[float, float] = (0.0, 2.0)
    handheld: bool = True
    shake_mm: float = 30.0
    shake_deg: float = 0.5
    noise_px: float = 1.5
    false_fraction: float = 0.03
    duration_s: float = 20.0
    speed_mps: float = 10.0  # mean speed along the path
    extent_m: float = 15.0  # horizontal amplitude per axis (the path stays within +-extent of its centre)
    climb_m: float = 4.0  # vertical amplitude
    altitude_m: float = 20.0  # height of the path's centre above the ground
    distance_m: tuple[float, float] = (30.0, 100.0)  # horizontal distance of each camera to the path's centre
    camera_height_m: float = 1.5
    image_width: int = 1920
    image_height: int = 1080
    focal_px: float = 1500.0


@dataclass(kw_only=True)
class FlightScene:
    """The path: position(t) = centre + sum_i amplitude[i] * sin(2 pi frequency[i] t + phase[i]) (per axis)."""

    centre: np.ndarray  # (3,) mm
    amplitude: np.ndarray  # (COMPONENTS, 3) mm
    frequency: np.ndarray  # (COMPONENTS, 3) Hz
    phase: np.ndarray  # (COMPONENTS, 3) rad
    camera_centres: np.ndarray  # (C, 3) base centres, mm

    def position(self, times: np.ndarray) -> np.ndarray:
        """(N, 1, 3) mm at global times (N,) s."""
        angle = 2 * np.pi * self.frequency[None] * np.asarray(times, dtype=float)[:, None, None] + self.phase[None]
        return (self.centre + (self.amplitude[None] * np.sin(angle)).sum(axis=1))[:, None, :]

    def velocity(self, times: np.ndarray) -> np.ndarray:
        """(N, 3) mm/s."""
        angle = 2 * np.pi * self.frequency[None] * np.asarray(times, dtype=float)[:, None, None] + self.phase[None]
        return (self.amplitude[None] * 2 * np.pi * self.frequency[None] * np.cos(angle)).sum(axis=1)


def _check(options: FlightOptions) -> None:
    problems = []
    if not (math.isfinite(options.duration_s) and 0 < options.duration_s <= 3600):
        problems.append(f"duration = {options.duration_s} s: must be within (0, 3600]")
    if not (options.speed_mps > 0 and options.extent_m > 0 and options.climb_m >= 0):
        problems.append("speed and extent must be positive, climb >= 0")
    low, high = options.distance_m
    if not (0 < low <= high):
        problems.append(f"camera distance {low}..{high} m: needs 0 < min <= max")
    if options.image_width < 2 or options.image_height < 2 or not options.focal_px > 0:
        problems.append("image size and focal length must be positive")
    if problems:
        raise DynreconError("invalid flight options: " + "; ".join(problems))


def flight_scene(options: FlightOptions, rng: np.random.Generator) -> FlightScene:
    """Draw the path and the cameras' base centres."""
    weights = rng.uniform(0.3, 1.0, (COMPONENTS, 3))
    weights /= weights.sum(axis=0)  # amplitudes of an axis add up to its extent
    amplitude = weights * np.array([options.extent_m, options.extent_m, options.climb_m]) * MM_PER_M
    frequency = rng.uniform(0.3, 1.0, (COMPONENTS, 3))
    phase = rng.uniform(0, 2 * np.pi, (COMPONENTS, 3))
    centre = np.array([0.0, 0.0, options.altitude_m * MM_PER_M])
    scene = FlightScene(
        centre=centre, amplitude=amplitude, frequency=frequency, phase=phase, camera_centres=np.zeros((0, 3))
    )
    # Frequencies scale the speed without changing the shape; the mean over a finite window is not exactly
    # linear in them, so iterate.
    grid = np.linspace(0.0, options.duration_s, 2001)
    for _ in range(SPEED_ITERATIONS):
        speed = float(np.linalg.norm(scene.velocity(grid), axis=1).mean()) / MM_PER_M
        scene.frequency = scene.frequency * (options.speed_mps / speed)
    C = options.cameras
    azimuth = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(C) / C + rng.uniform(-0.2, 0.2, C)
    distance = rng.uniform(options.distance_m[0], options.distance_m[1], C) * MM_PER_M
    scene.camera_centres = np.stack(
        [distance * np.cos(azimuth), distance * np.sin(azimuth), np.full(C, options.camera_height_m * MM_PER_M)], axis=1
    )
    return scene


def simulate_flight(options: FlightOptions | None = None) -> tuple[SimulatedCapture, CaptureRecord, FlightScene]:
    """The scene and its capture: cameras look at the path's centre (then shake if handheld)."""
    options = options or FlightOptions()
    _check(options)
    rng = np.random.default_rng(options.seed)
    scene = flight_scene(options, rng)
    poses = [look_at(c, scene.centre, UP) for c in scene.camera_centres]
    K = np.array(
        [
            [options.focal_px, 0, (options.image_width - 1) / 2],
            [0, options.focal_px, (options.image_height - 1) / 2],
            [0, 0, 1.0],
        ]
    )

    def valid(times: np.ndarray) -> np.ndarray:
        return np.ones(len(times), dtype=bool)

    capture, record = capture_scene(
        scene.position,
        valid,
        (0.0, options.duration_s),
        ["drone"],
        K,
        np.stack([p[0] for p in poses]),
        np.stack([p[1] for p in poses]),
        (options.image_width, options.image_height),
        options,
        rng,
        min_depth=MIN_DEPTH_MM,
    )
    return capture, record, scene


def run(out_dir: str | Path, options: FlightOptions | None = None) -> Path:
    """Simulate the flight into `out_dir` (cameras.json, tracks.csv, truth.csv, clocks_truth.json,
    simulation.json); returns out_dir."""
    options = options or FlightOptions()
    capture, record, scene = simulate_flight(options)
    speeds = np.linalg.norm(scene.velocity(np.linspace(0, options.duration_s, 2001)), axis=1) / MM_PER_M
    simulation = {
        "mode": "flight",
        "units": "mm",
        "options": options_record(options),
        "path": {
            "centre_mm": scene.centre.tolist(),
            "amplitude_mm": scene.amplitude.tolist(),
            "frequency_hz": scene.frequency.tolist(),
            "phase_rad": scene.phase.tolist(),
            "mean_speed_mps": float(speeds.mean()),
            "max_speed_mps": float(speeds.max()),
        },
        "camera_centres_mm": scene.camera_centres.tolist(),
    }
    return write_capture(Path(out_dir), capture, record, simulation, time_origin="the start of the flight")
