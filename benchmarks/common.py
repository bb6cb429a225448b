"""Shared helpers of the solver benchmarks (paper_tables.py, solver_speed.py): the mocap windows, resampling,
the paper's numbers, one simulate-solve-evaluate run and table formatting.

Not a package module: the scripts put the repository root on sys.path and import this file as `common`.
"""

from __future__ import annotations

import logging
import re
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reconstruct.inputs import build_problem  # noqa: E402
from reconstruct.outputs.mocap import Mocap, read_mocap  # noqa: E402
from reconstruct.outputs.points import FramePoints  # noqa: E402
from reconstruct.solver.alternation import SolveResult, SolverOptions, solve  # noqa: E402
from reconstruct.solver.initialize import fill_missing_points  # noqa: E402
from reconstruct.solver.problem import Problem  # noqa: E402
from reconstruct.stage import frame_points  # noqa: E402
from simulation.evaluate import THRESHOLDS_MM, evaluate  # noqa: E402
from simulation.simulate import SimulatedCapture, SimulationOptions, simulate_mocap  # noqa: E402

log = logging.getLogger(__name__)

MOCAP_DIR = ROOT.parent / "shared" / "data" / "mocap"
# The paper's protocol: 4 cameras, 30 Hz each = 120 captures per second in total.
BASE_RATE_HZ = 120.0
CAMERAS = 4


def solver_version() -> str:
    """HEAD commit and whether reconstruct/ has uncommitted changes: the solver is tuned while benchmarks run."""
    import subprocess

    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "reconstruct"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return f"{head}{' + uncommitted changes in reconstruct/' if dirty else ''}"


# Modules of reconstruct/ before it was split by concern (solver/, clocks/, outputs/, simulation/), for
# module_at_revision on older revisions.
PRE_SPLIT_MODULES = {
    "reconstruct.anderson": "reconstruct.solver.anderson",
    "reconstruct.candidates": "reconstruct.solver.candidates",
    "reconstruct.initialize": "reconstruct.solver.initialize",
    "reconstruct.problem": "reconstruct.solver.problem",
    "reconstruct.rays": "reconstruct.solver.rays",
    "reconstruct.simplex": "reconstruct.solver.simplex",
    "reconstruct.working_set": "reconstruct.solver.active_set",
    "reconstruct.wstep": "reconstruct.solver.wstep",
    "reconstruct.xstep": "reconstruct.solver.xstep",
    "reconstruct.solver": "reconstruct.solver.alternation",
    "reconstruct.clocks": "reconstruct.clocks.estimate",
    "reconstruct.clock_search": "reconstruct.clocks.search",
    "reconstruct.refine": "reconstruct.trajectory",
    "reconstruct.points": "reconstruct.outputs.points",
    "reconstruct.mocap": "reconstruct.outputs.mocap",
    "reconstruct.solve_stage": "reconstruct.stage",
    "reconstruct.simulate": "simulation.simulate",
}


def module_at_revision(relative_path: str, revision: str, name: str) -> ModuleType:
    """`relative_path` (e.g. reconstruct/solver/rays.py) as of a git revision, loaded as module `name`, for benchmarks
    that compare a rewrite with the code it replaced on the same inputs."""
    import importlib.util
    import subprocess
    import tempfile

    def show(path: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["git", "show", f"{revision}:{path}"], cwd=ROOT, capture_output=True, text=True)

    shown = show(relative_path)
    if shown.returncode != 0:  # a revision before reconstruct/ was split by concern: its flat module, imports mapped
        module_name = relative_path.removesuffix(".py").replace("/", ".")
        old_names = [old for old, new in PRE_SPLIT_MODULES.items() if new == module_name]
        if not old_names or (shown := show(old_names[0].replace(".", "/") + ".py")).returncode != 0:
            raise SystemExit(f"cannot find {relative_path} at {revision}")
    source = re.sub(
        r"(?<![\w.])(reconstruct\.\w+)", lambda m: PRE_SPLIT_MODULES.get(m.group(1), m.group(1)), shown.stdout
    )
    path = Path(tempfile.mkdtemp()) / f"{name}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot load {relative_path} at {revision}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def solver_sources_digest() -> str:
    """A digest of what a solve depends on, every file of reconstruct/ and this one: the key of cached solves, which
    also tells apart two working trees with different uncommitted changes (solver_version cannot)."""
    import hashlib

    digest = hashlib.sha256()
    for path in [*sorted((ROOT / "reconstruct").rglob("*.py")), Path(__file__).resolve()]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def require_mocap_dir() -> Path:
    """The shared mocap folder, or exit with a message saying where it was expected."""
    if not MOCAP_DIR.is_dir():
        sys.exit(
            f"motion-capture data not found at {MOCAP_DIR}: these benchmarks need ../shared/data/mocap "
            "beside the repository (see its README.md)"
        )
    return MOCAP_DIR


@dataclass(frozen=True, kw_only=True)
class Window:
    """A stretch of one mocap file: `seconds` of motion from `start_s` (the file's clock, from its first sample)."""

    name: str  # short label for tables
    path: str  # relative to MOCAP_DIR
    motion: str
    start_s: float
    seconds: float = 2.5  # 300 captures at 120 Hz


# Fixed list: the paper's database (HDM05), CMU, then gait-lab files of different motions. The default run uses
# the first 6. Files whose rate is a multiple of 120 Hz are stepped as they are; the others are resampled to
# 120 Hz (cubic spline per coordinate) so that every window is seen at exactly 30 / 15 / 7.5 Hz per camera.
WINDOWS: tuple[Window, ...] = (
    Window(
        name="hdm05",
        path="hdm05/HDM_dg_06-03_03_120.c3d",
        motion="HDM05 clip (whole file, 202 frames)",
        start_s=0.0,
        seconds=202 / 120,
    ),
    Window(name="cmu-jumps", path="cmu/cmu_01_01.c3d", motion="playground jumps", start_s=5.0),
    Window(name="squat", path="lab/gatech_vicon/sehoon_squat.c3d", motion="squats", start_s=5.0),
    Window(
        name="run-5ms",
        path="lab/sprinter/run0500cms.trc",
        motion="running 5 m/s (250 Hz, resampled)",
        start_s=0.0,
        seconds=2.2,
    ),
    Window(
        name="dropjump", path="lab/opencap_lab_subject4/DJ1.trc", motion="drop jump (100 Hz, resampled)", start_s=0.0
    ),
    Window(
        name="walk",
        path="lab/misc/addbio_tutorial_walk.trc",
        motion="walking (100 Hz, resampled)",
        start_s=0.0,
        seconds=2.3,
    ),
    Window(name="freeform", path="lab/gatech_vicon/nick_freeform_001.c3d", motion="free-form movement", start_s=2.5),
    Window(
        name="run-4ms",
        path="lab/hamner2010_s04/run400.trc",
        motion="running 4 m/s (100 Hz, resampled)",
        start_s=0.0,
        seconds=2.05,
    ),
    Window(name="cmu-late", path="cmu/cmu_01_01.c3d", motion="playground jumps, later part", start_s=15.0),
    Window(
        name="sit-stand",
        path="lab/opencap_lab_subject4/STS1.trc",
        motion="sit-to-stand (100 Hz, resampled)",
        start_s=3.0,
    ),
)


def load_window(window: Window) -> Mocap:
    """The window as a Mocap at a rate that is a multiple of 120 Hz (resampled to 120 Hz when the file's is not)."""
    mocap = read_mocap(require_mocap_dir() / window.path)
    factor = mocap.rate / BASE_RATE_HZ
    if abs(factor - round(factor)) < 1e-9 and round(factor) >= 1:
        first = round(window.start_s * mocap.rate)
        count = round(window.seconds * mocap.rate)
        if first + count > mocap.num_frames:
            raise ValueError(f"{window.path}: window {window.start_s}+{window.seconds} s runs past the file's end")
        index = np.arange(first, first + count)
        return replace(mocap, xyz=mocap.xyz[index].copy(), times=mocap.times[index] - mocap.times[first])
    return resample(mocap, BASE_RATE_HZ, window.start_s, window.seconds)


def resample(mocap: Mocap, rate: float, start_s: float, seconds: float) -> Mocap:
    """`seconds` of motion from `start_s` resampled at `rate` by a cubic spline per marker coordinate.

    A resampled sample is NaN unless the four original samples around it are all present, so a gap is never
    bridged by the spline.
    """
    from scipy.interpolate import CubicSpline

    clock = mocap.times - mocap.times[0]
    count = round(seconds * rate)
    times = start_s + np.arange(count) / rate
    if times[-1] > clock[-1] + 1e-9:
        raise ValueError(f"{mocap.path}: window {start_s}+{seconds} s runs past the file's end ({clock[-1]:.2f} s)")
    xyz = np.full((count, mocap.num_markers, 3), np.nan)
    missing = mocap.missing()
    right = np.clip(np.searchsorted(clock, times), 1, len(clock) - 1)  # clock[right - 1] <= t <= clock[right]
    around = np.clip(right[:, None] + np.arange(-2, 2)[None, :], 0, len(clock) - 1)  # (count, 4)
    for m in range(mocap.num_markers):
        known = ~missing[:, m]
        if known.sum() < 4:
            continue
        spline = CubicSpline(clock[known], mocap.xyz[known, m], axis=0)
        ok = known[around].all(axis=1)
        xyz[ok, m] = spline(times[ok])
    return replace(mocap, xyz=xyz, rate=rate, times=times - start_s)


def step_for(mocap: Mocap, per_camera_hz: float) -> int:
    """Mocap step that gives `per_camera_hz` per camera with CAMERAS cameras (the rate is a multiple of 120)."""
    step = mocap.rate / (per_camera_hz * CAMERAS)
    if abs(step - round(step)) > 1e-9 or round(step) < 1:
        raise ValueError(f"{mocap.rate} Hz cannot be stepped to {per_camera_hz} Hz per camera")
    return round(step)


@dataclass(frozen=True, kw_only=True)
class CaptureSetting:
    """One simulated condition of the paper's protocol: frame rate per camera, pixel noise, missing share, camera
    assignment (the rows of paper_tables.py, refine_tables.py and trust.py)."""

    key: str
    label: str
    per_camera_hz: float = 30.0
    noise_px: float = 0.0
    miss: float = 0.0
    unconstrained: bool = False

    def simulation_options(self, mocap: Mocap, seed: int, camera_distance_mm: float | None) -> SimulationOptions:
        return SimulationOptions(
            step=step_for(mocap, self.per_camera_hz),
            noise_px=self.noise_px,
            miss=self.miss,
            unconstrained=self.unconstrained,
            seed=seed,
            camera_distance_mm=camera_distance_mm,
        )


# The paper's tables (HDM05, 4 cameras), share of points under 10, 20, 30, 40, 50, 100 mm:
# /work/shared/notes/solver-math.md. Keys are the row keys of paper_tables.py.
PAPER: dict[str, tuple[float, ...]] = {
    "30Hz": (0.9933, 0.9975, 0.9986, 0.9991, 0.9994, 0.9998),
    "15Hz": (0.9734, 0.9850, 0.9899, 0.9926, 0.9944, 0.9979),
    "7.5Hz": (0.9036, 0.9415, 0.9568, 0.9655, 0.9711, 0.9833),
    "30Hz-unconstrained": (0.9766, 0.9905, 0.9947, 0.9963, 0.9971, 0.9990),
    "noise1": (0.9529, 0.9925, 0.9974, 0.9987, 0.9992, 0.9998),
    "noise2": (0.7878, 0.9568, 0.9869, 0.9949, 0.9976, 0.9997),
    "noise3": (0.6074, 0.8855, 0.9593, 0.9828, 0.9917, 0.9991),
    "noise4": (0.4601, 0.7941, 0.9144, 0.9602, 0.9797, 0.9980),
    "noise5": (0.3551, 0.7008, 0.8590, 0.9287, 0.9615, 0.9966),
    "missing0": (0.9933, 0.9975, 0.9986, 0.9991, 0.9994, 0.9998),
    "missing10": (0.9901, 0.9961, 0.9975, 0.9982, 0.9986, 0.9993),
    "missing20": (0.9835, 0.9910, 0.9936, 0.9948, 0.9955, 0.9968),
    "missing30": (0.9594, 0.9740, 0.9788, 0.9813, 0.9829, 0.9868),
    "missing40": (0.9074, 0.9331, 0.9438, 0.9493, 0.9529, 0.9626),
    "missing50": (0.7734, 0.8313, 0.8560, 0.8703, 0.8798, 0.9050),
}


def simulate(mocap: Mocap, options: SimulationOptions) -> tuple[SimulatedCapture, Problem, float]:
    """Simulate a capture of the whole `mocap` and assemble the solver's problem (frames in the truth's order);
    also returns the camera distance in mm (1 px of noise is about distance / 1000 mm at the subject)."""
    capture, rig = simulate_mocap(mocap, options)
    problem = build_problem(capture.cameras, capture.tracks, point_names=capture.truth.point_names)
    return capture, problem, rig.distance


@dataclass(kw_only=True)
class RunResult:
    shares: list[float]  # (6,) solver, share under THRESHOLDS_MM
    init_shares: list[float]  # (6,) initialization only (missing points interpolated as the solver starts)
    median_mm: float
    frames: int
    points: int
    seconds: float
    iterations: list[int]  # per stage
    timings: dict[str, float]

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def solve_and_score(
    capture: SimulatedCapture, problem: Problem, options: SolverOptions | None = None
) -> tuple[RunResult, SolveResult]:
    started = time.perf_counter()
    result = solve(problem, options or SolverOptions())
    seconds = time.perf_counter() - started
    accuracy = evaluate(frame_points(problem, result), capture.truth)
    init_xyz = fill_missing_points(result.init_points, problem.video_index)
    init_fp = FramePoints(
        videos=problem.frame_videos,
        frames=problem.frames,
        point_names=problem.point_names,
        xyz=init_xyz,
        observed=problem.observed,
    )
    init_accuracy = evaluate(init_fp, capture.truth)
    run = RunResult(
        shares=[float(s) for s in accuracy.share_under],
        init_shares=[float(s) for s in init_accuracy.share_under],
        median_mm=accuracy.median,
        frames=problem.num_frames,
        points=problem.num_points,
        seconds=seconds,
        iterations=[s.iterations for s in result.stages],
        timings=dict(result.timings),
    )
    return run, result


def percent_row(label: str, shares: tuple[float, ...] | list[float] | np.ndarray, extra: str = "") -> str:
    cells = " | ".join("—" if not np.isfinite(s) else f"{100 * s:.2f}" for s in shares)
    return f"| {label} | {cells} |{extra}"


def threshold_header(first: str, extra: str = "") -> str:
    names = " | ".join(f"<{t:g} mm" for t in THRESHOLDS_MM)
    dashes = "|---" * (len(THRESHOLDS_MM) + 1 + (1 if extra else 0))
    head = f"| {first} | {names} |" + (f" {extra} |" if extra else "")
    return head + "\n" + dashes + "|"
