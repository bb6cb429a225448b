"""`dynrecon demo`: the whole job on the embedded video sample, from a fresh clone, in a few minutes.

The sample (`data_samples/video_sample/`, made by `data_samples/make_video_sample.py`): three unsynchronized
handheld videos (30, 24 and 20 fps, different start times) of a figure walking on a treadmill in a textured room,
the points a user would have clicked, the true 3D joints and the true cameras. The demo runs `dynrecon run` on it
(register -> track -> solve -> record -> export) into a fresh folder and scores the 3D points against the truth.
The registered world has its own origin, orientation and scale, so the scoring first moves the points by the
similarity that maps the registered cameras onto the true ones (`dynrecon.truth.similarity_to_truth`).

`--simulated`: the fast variant without videos: the procedural walker seen by 4 simulated
unsynchronized cameras (30 Hz each, interleaved, never two at once), solved without any timing.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, replace
from pathlib import Path

from dynrecon.atomic import atomic_write_text, require_writable
from dynrecon.errors import DynreconError, InputError
from dynrecon.pipeline import PipelineOptions, PipelineResult, default_register, run_stages, score_against_truth
from labeling.skeleton import read_skeleton
from reconstruct.clocks.estimate import ClockModel, ClockOptions, SearchMode
from reconstruct.stage import SolveOptions
from reconstruct.stage import run as solve_run
from reconstruct.temporal import Refinement, TemporalOptions
from sfm.options import ALL_CORES
from simulation import evaluate, simulate

log = logging.getLogger(__name__)

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
VIDEO_SAMPLE = SAMPLES / "video_sample"
VIDEO_NAMES = ("cam0", "cam1", "cam2")
# SfM frames per video: enough to register every frame of the sample (the others by PnP); more only cost time.
SFM_FRAMES = 12
SIMULATED_NOISE_PX = 0.5  # --simulated: a little pixel noise, as clicked or tracked points have
SIMULATED_SEED = 0


@dataclass(kw_only=True)
class DemoOptions:
    simulated: bool = False  # the fast simulated-camera variant instead of the videos
    sample: Path = VIDEO_SAMPLE  # a folder laid out like data_samples/video_sample (the tests use a shorter one)
    # COLMAP threads of the registration (-1: all cores). Several threads are faster but not reproducible (the
    # cameras, and so the score, vary from run to run); one thread gives the same cameras every run.
    sfm_threads: int = ALL_CORES


@dataclass(kw_only=True)
class DemoResult:
    workspace: Path
    accuracy: evaluate.ReconstructionAccuracy
    pipeline: PipelineResult | None = None  # None for --simulated

    @property
    def recording(self) -> Path:
        return self.workspace / "recording.rrd"


def fresh_folder(base: Path) -> Path:
    """`base`, or `base-2`, `base-3`, ... : never write into a folder that already has results."""
    candidate, number = base, 1
    while candidate.exists() and (not candidate.is_dir() or any(candidate.iterdir())):  # a file is taken too
        number += 1
        candidate = base.with_name(f"{base.name}-{number}")
    require_writable(candidate)  # one line, not a traceback, where it cannot be made
    candidate.mkdir(parents=True, exist_ok=True)
    return candidate


def _sample_files(sample: Path) -> list[Path]:
    wanted = [sample / f"{name}.mp4" for name in VIDEO_NAMES]
    wanted += [sample / name for name in ("labels.csv", "truth.csv", "truth_cameras.json", "walker_skeleton.json")]
    missing = [path for path in wanted if not path.is_file()]
    if missing and sample.resolve() != VIDEO_SAMPLE.resolve():
        raise InputError(missing[0], "not found", fix="--sample names a folder laid out like data_samples/video_sample")
    if missing:
        raise DynreconError(
            f"{missing[0]}: the embedded video sample is incomplete "
            "(regenerate it with `python data_samples/make_video_sample.py`)"
        )
    return wanted[: len(VIDEO_NAMES)]


def pipeline_options(sample: Path, sfm_threads: int = ALL_CORES) -> PipelineOptions:
    register = replace(default_register(), max_frames=SFM_FRAMES, num_threads=sfm_threads)
    # Clocks: offset only (the sample's decoder times are exact: no rate to fit), from the solve's W links. The
    # treadmill walk is periodic, so the default affine clocks and the track search can lock a whole step off,
    # and the refinement on such clocks moves the points far off.
    clocks = ClockOptions(model=ClockModel.OFFSET, search=SearchMode.NEVER)
    solve = SolveOptions(recording=None, temporal=TemporalOptions(refinement=Refinement.CLOCKS, clocks=clocks))
    return PipelineOptions(
        register=register, solve=solve, labels=sample / "labels.csv", skeleton=sample / "walker_skeleton.json"
    )


def run_video(out_dir: Path, options: DemoOptions) -> DemoResult:
    videos = _sample_files(options.sample)
    ws = fresh_folder(out_dir)
    result = run_stages(list(videos), ws, pipeline_options(options.sample, options.sfm_threads))
    accuracy = score_against_truth(ws, options.sample / "truth.csv", options.sample / "truth_cameras.json")
    atomic_write_text(
        ws / "accuracy.json",
        json.dumps(
            {
                "truth": str(options.sample / "truth.csv"),
                "units": "mm",
                "alignment": "similarity of the registered cameras onto the true cameras",
                **accuracy.as_dict(),
            },
            indent=1,
        )
        + "\n",
    )
    return DemoResult(workspace=ws, accuracy=accuracy, pipeline=result)


def run_simulated(out_dir: Path, options: DemoOptions) -> DemoResult:
    mocap = SAMPLES / "walker.trc"
    if not mocap.is_file():
        raise DynreconError(f"{mocap}: the embedded sample is missing (run `python data_samples/make_walker.py`)")
    out_dir = fresh_folder(out_dir)
    simulate.run(mocap, out_dir, simulate.SimulationOptions(noise_px=SIMULATED_NOISE_PX, seed=SIMULATED_SEED))
    skeleton = tuple(read_skeleton(SAMPLES / "walker_skeleton.json").connections)
    solve_run(out_dir / "cameras.json", out_dir / "tracks.csv", out_dir, SolveOptions(skeleton=skeleton))
    return DemoResult(workspace=out_dir, accuracy=evaluate.run(out_dir))


def run(out_dir: Path, options: DemoOptions | None = None) -> DemoResult:
    options = options or DemoOptions()
    return run_simulated(out_dir, options) if options.simulated else run_video(out_dir, options)
