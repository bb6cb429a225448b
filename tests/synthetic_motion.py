"""Smooth synthetic motion for solver tests: no shared data needed, ground truth fully known."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reconstruct.inputs import build_problem
from reconstruct.outputs.points import FramePoints
from reconstruct.solver.problem import Problem
from simulation.simulate import SimulationOptions, simulate_capture


def smooth_motion(frames: int = 160, points: int = 8, seed: int = 0, rate: float = 120.0) -> np.ndarray:
    """(T, P, 3) mm: points of a ~1 m body swaying smoothly (sinusoids of 0.3-1 Hz, 200 mm amplitude)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / rate
    base = rng.normal(size=(points, 3)) * 300.0 + np.array([0.0, 0.0, 1000.0])
    frequency = rng.uniform(0.3, 1.0, size=(points, 3))
    phase = rng.uniform(0.0, 2 * np.pi, size=(points, 3))
    return base[None] + 200.0 * np.sin(2 * np.pi * frequency[None] * t[:, None, None] + phase[None])


def synthetic_problem(
    frames: int = 160, points: int = 8, seed: int = 0, **options: float
) -> tuple[Problem, FramePoints]:
    """A simulated 4-camera capture of `smooth_motion` and its truth aligned to the problem's frame order."""
    capture = simulate_capture(smooth_motion(frames, points, seed), 120.0, SimulationOptions(seed=seed, **options))  # type: ignore[arg-type]
    problem = build_problem(capture.cameras, capture.tracks, point_names=capture.truth.point_names)
    return problem, capture.truth


def truth_array(problem: Problem, truth: FramePoints) -> np.ndarray:
    """(F, P, 3) truth in the problem's frame order."""
    index = truth.index()
    return np.stack([truth.xyz[index[(v, int(f))]] for v, f in zip(problem.frame_videos, problem.frames, strict=True)])


def share_within_10mm(points: np.ndarray, truth: np.ndarray) -> float:
    """Share of the finite points `(F, P, 3)` within 10 mm of `truth`."""
    error = np.linalg.norm(points - truth, axis=-1)
    return float(np.mean(error[np.isfinite(error)] < 10.0))


def simulated_phones(out: Path, rate: float = 120.0, noise_px: float = 0.0) -> Path:
    """`dynrecon simulate --mode phones` of 1.5 s of an 8-point smooth motion: three static phones at 30, 25 and
    20 fps with known clocks (offsets 0-0.3 s), `noise_px` of pixel noise. Returns the simulation folder
    (cameras.json, tracks.csv, clocks_truth.json)."""
    from dynrecon.cli import main
    from reconstruct.outputs.mocap import Mocap, write_trc

    xyz = smooth_motion(frames=180, points=8, rate=rate)
    source = write_trc(
        out / "motion.trc",
        Mocap(xyz=xyz, rate=rate, marker_names=[f"m{i}" for i in range(8)], times=np.arange(180) / rate),
        units="mm",
    )
    if (
        main(
            [
                "simulate",
                str(source),
                "--out",
                str(out / "sim"),
                "--mode",
                "phones",
                "--cameras",
                "3",
                "--fps",
                "30,25,20",
                "--offsets",
                "0,0.3",
                "--seed",
                "2",
                "--noise",
                str(noise_px),
            ]
        )
        != 0
    ):
        raise RuntimeError("the phone simulation failed")
    return out / "sim"
