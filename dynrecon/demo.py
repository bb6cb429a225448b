"""`dynrecon demo`: the whole job on the embedded video sample, from a fresh clone, in a few minutes.

The sample (`data_samples/video_sample/`, made by `data_samples/make_video_sample.py`): three unsynchronized
handheld videos (30, 24 and 20 fps, different start times) of a figure walking on a treadmill in a textured room,
the points a user would have clicked, the true 3D joints and the true cameras. The demo runs `dynrecon run` on it
(register -> track -> solve -> record -> export) into a fresh folder and scores the 3D points against the truth.
The registered world has its own origin, orientation and scale, so the scoring first moves the points by the
similarity that maps the registered cameras onto the true ones (`dynrecon.pipeline.similarity_to_truth`).

`--simulated`: the fast (~30 s) variant without videos: the procedural walker seen by 4 simulated
unsynchronized cameras (30 Hz each, interleaved, never two at once), solved without any timing.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import DynreconError
from dynrecon.pipeline import PipelineOptions, PipelineResult, _default_register, run_stages, score_against_truth
from labeling.workspace import read_skeleton
from reconstruct.clocks.estimate import ClockModel, ClockOptions, SearchMode
from reconstruct.stage import SolveStageOptions
from reconstruct.stage import run as solve_run
from reconstruct.temporal import Refinement, TemporalOptions
from sfm.register import ALL_CORES
from simulation import evaluate, simulate

log = logging.getLogger(__name__)

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
VIDEO_SAMPLE = SAMPLES / "video_sample"
VIDEO_NAMES = ("cam0", "cam1", "cam2")
# SfM frames per video: 12 of the 36-57 register every frame of the sample (the others by PnP) in about 2 min on
# 2 cores; more frames cost minutes and did not change the accuracy measurably (see the module's tests).
SFM_FRAMES = 12


@dataclass(kw_only=True)
class DemoOptions:
    simulated: bool = False  # the fast simulated-camera variant instead of the videos
    noise_px: float = 0.5  # --simulated: a little pixel noise, as clicked or tracked points have
    seed: int = 0  # --simulated
    sample: Path = VIDEO_SAMPLE  # a folder laid out like data_samples/video_sample (the tests use a shorter one)
    # COLMAP threads of the registration (-1: all cores). Several threads are not reproducible: on the full sample
    # two runs gave 90.3 / 90.5 % < 10 mm (83-85 s), but on the tests' 1 s cut five runs gave 21-77 % (camera
    # centres 15-28 mm and focal lengths 0.5-2.2 % off; the tracks identical, and the solver scored the same on
    # each registration). One thread gives the same cameras every run (full sample: 90.4 %, 105 s).
    sfm_threads: int = ALL_CORES


@dataclass(kw_only=True)
class DemoResult:
    workspace: Path
    accuracy: evaluate.Accuracy
    pipeline: PipelineResult | None = None  # None for --simulated

    @property
    def recording(self) -> Path:
        return self.workspace / "recording.rrd"


def fresh_folder(base: Path) -> Path:
    """`base`, or `base-2`, `base-3`, ... : never write into a folder that already has results."""
    candidate, number = base, 1
    while candidate.exists() and any(candidate.iterdir()):
        number += 1
        candidate = base.with_name(f"{base.name}-{number}")
    candidate.mkdir(parents=True, exist_ok=True)
    return candidate


def _sample_files(sample: Path) -> list[Path]:
    wanted = [sample / f"{name}.mp4" for name in VIDEO_NAMES]
    wanted += [sample / name for name in ("labels.csv", "truth.csv", "truth_cameras.json", "walker_skeleton.json")]
    missing = [path for path in wanted if not path.is_file()]
    if missing:
        raise DynreconError(f"{missing[0]}: the embedded video sample is incomplete "
                            "(regenerate it with `python data_samples/make_video_sample.py`)")
    return wanted[:len(VIDEO_NAMES)]


def pipeline_options(sample: Path, sfm_threads: int = ALL_CORES) -> PipelineOptions:
    register = _default_register()
    register.max_frames = SFM_FRAMES
    register.num_threads = sfm_threads
    # Clocks: offset only (the sample's decoder times are exact: no rate to fit), from the solve's W links. The
    # treadmill walk is periodic (a step every 0.56 s): with the default affine clocks and track search, cam1 came
    # out 1.69 s (three steps) off and cam2 at rate 0.73, and the refinement on those clocks put the points
    # 0.1-0.2 m off. Measured on the full sample (same registration and tracks): 4.4 % < 10 mm with the default
    # clock options, 82.7 % with no refinement, 90.3 % with offset-only clocks (with or without the search).
    clocks = ClockOptions(model=ClockModel.OFFSET, search=SearchMode.NEVER)
    solve = SolveStageOptions(recording=False, temporal=TemporalOptions(refinement=Refinement.CLOCKS, clocks=clocks))
    return PipelineOptions(register=register, solve=solve, labels=sample / "labels.csv",
                           skeleton=sample / "walker_skeleton.json")


def run_video(out_dir: Path, options: DemoOptions) -> DemoResult:
    videos = _sample_files(options.sample)
    ws = fresh_folder(out_dir)
    result = run_stages(list(videos), ws, pipeline_options(options.sample, options.sfm_threads))
    accuracy = score_against_truth(ws, options.sample / "truth.csv", options.sample / "truth_cameras.json")
    atomic_write_text(ws / "accuracy.json", json.dumps(
        {"truth": str(options.sample / "truth.csv"), "units": "mm",
         "alignment": "similarity of the registered cameras onto the true cameras", **accuracy.as_dict()},
        indent=1) + "\n")
    return DemoResult(workspace=ws, accuracy=accuracy, pipeline=result)


def run_simulated(out_dir: Path, options: DemoOptions) -> DemoResult:
    mocap = SAMPLES / "walker.trc"
    if not mocap.is_file():
        raise DynreconError(f"{mocap}: the embedded sample is missing (run `python data_samples/make_walker.py`)")
    out_dir = fresh_folder(out_dir)
    simulate.run(mocap, out_dir, simulate.SimulationOptions(noise_px=options.noise_px, seed=options.seed))
    skeleton = tuple(read_skeleton(SAMPLES / "walker_skeleton.json").connections)
    solve_run(out_dir / "cameras.json", out_dir / "tracks.csv", out_dir, SolveStageOptions(skeleton=skeleton))
    return DemoResult(workspace=out_dir, accuracy=evaluate.run(out_dir))


def run(out_dir: Path, options: DemoOptions | None = None) -> DemoResult:
    options = options or DemoOptions()
    return run_simulated(out_dir, options) if options.simulated else run_video(out_dir, options)


def add_command(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the whole job on the embedded video sample and score it",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("dynrecon-demo"),
                        help="folder for the results (a fresh one is made beside it if it has results)")
    parser.add_argument("--simulated", action="store_true",
                        help="simulated cameras instead of the videos: no registration or tracking (~30 s)")
    parser.add_argument("--sample", type=Path, default=VIDEO_SAMPLE,
                        help="a folder laid out like data_samples/video_sample (default: that one)")
    parser.add_argument("--threads", type=int, default=DemoOptions().sfm_threads,
                        help="COLMAP threads of the registration (default -1: all cores; 1: the same cameras on "
                             "every run, ~25 %% slower)")
    parser.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    result = run(args.out, DemoOptions(simulated=args.simulated, sample=args.sample, sfm_threads=args.threads))
    seconds = time.perf_counter() - started
    if result.pipeline is None:
        print(f"demo (--simulated): 4 unsynchronized simulated cameras, walker sample, solved in "  # noqa: T201
              f"{seconds:.0f} s")
    else:
        stages = ", ".join(f"{s.name} {s.seconds:.0f} s" for s in result.pipeline.stages)
        print(f"demo: 3 unsynchronized handheld videos (30/24/20 fps) of the video sample, {seconds:.0f} s "  # noqa: T201
              f"({stages})")
        print("points moved into the sample's true frame by the similarity (scale, rotation, translation) that "  # noqa: T201
              "maps the registered cameras onto the true ones")
    print(f"accuracy vs ground truth, {result.accuracy.count} points (mm): {result.accuracy.table()}")  # noqa: T201
    print(f"results in {result.workspace}")  # noqa: T201
    print(f"open the recording with: rerun {result.recording}")  # noqa: T201
    return 0
