"""`dynrecon run`: videos in, 3D motion out. register -> (track) -> solve -> record -> export, in one workspace.

Each stage is skipped when its outputs exist unchanged and its inputs (file contents and options) are those of the
last run: `WS/pipeline.json` keeps, per stage, a hash of its inputs and of each output file. So a user can
register, label, and rerun: only what the new labels change is redone. `force` redoes everything.

Workspace layout (paths relative to WS):
    register/          cameras.json, background.ply, register_report.json, frames/, sfm/ (dynrecon register)
    labels.csv         the clicks (from the labeling page, or a copy of --labels)
    tracks.csv         written by the track stage (labels tracked, or --board's corners), or a copy of --tracks
    points3d.csv, sequencing.json, report.json    the solve stage
    recording.rrd      the rerun recording (background cloud, videos, tracks, 3D points, skeleton)
    points.trc, points.c3d                        exports in the estimated global order
    pipeline.json      stage hashes and timings

Registration does not use the tracks for masks, so that new labels never force a new registration (the video
sample registers every frame without masks). When the background leaves a static video out (or poses
fewer than two videos) and there are labels or tracks, the `subject` stage registers again after tracking, with
the subject's tracks (`sfm.subject`), into register_subject/; later stages then use its cameras.json. The same when
the tracks number people per video (`import-tracks --person all`): registration matches them across the videos
(with a lab calibration the `subject` stage adds the people's maps to the calibration's cameras).

With `PipelineOptions.calibration` (a lab calibration, any file `dynrecon import-calibration` reads), the `register`
stage imports it instead of running SfM: register/cameras.json gives every frame its camera's fixed pose, and the
stage's hash covers the calibration's contents.

The public API (`__all__`): `run` / `run_stages` run everything; `Stages` is the same pipeline one stage at a time
(`register`, `track`, `subject`, `solve`, `record`, `export`, or `finish` for all after `register`), for a task
graph of one's own (the `batch` package builds its Dask graph from it; docs/scaling.md has an example).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon import video_io
from dynrecon.atomic import atomic_open, keep_aside, require_writable
from dynrecon.errors import InputError
from dynrecon.jsonvalues import float_or_nan
from dynrecon.pipeline_state import STATE_NAME, State, file_hash, inputs_key
from dynrecon.truth import Similarity, align_to_truth, score_points, similarity_to_truth
from labeling.skeleton import read_skeleton
from reconstruct.clocks.model import frame_periods
from reconstruct.outputs.export import (
    OrderSource,
    check_units,
    clock_note,
    clock_times,
    frame_times,
    global_order,
    measured_only,
    write_c3d_export,
    write_trc_export,
)
from reconstruct.outputs.points import read_points, read_sequencing
from reconstruct.outputs.recording import BackgroundCloud, write_recording
from reconstruct.stage import SolveOptions, solve
from reconstruct.views import nearest_gap
from sfm.board_hint import board_hint
from sfm.calibration import run as import_calibration
from sfm.calibration_dlt import is_dlt
from sfm.cameras import CameraSet, read_cameras
from sfm.export import read_ply, write_ply
from sfm.options import CalibrationFormat, ImportCalibrationOptions
from sfm.people import per_video_people
from sfm.register_check import refuted_in_folder
from sfm.register_markers import MARKER_TRACKS
from sfm.register_people import people_on_cameras
from sfm.register_subject import TRACK_ADVICE
from sfm.stage import Localize, RegisterOptions, RegistrationError, board_tracks, check_scale_points
from sfm.stage import run as register_run
from simulation.evaluate import ReconstructionAccuracy
from tracking.charuco import read_charuco_board
from tracking.labels import read_labels
from tracking.options import TrackOptions
from tracking.stage import run as track_run
from tracking.tracks import Tracks, matched_to_videos, read_tracks

log = logging.getLogger(__name__)

REGISTER_DIR = "register"
SUBJECT_DIR = "register_subject"
# "subject" runs only when the background left a static video out and there are tracks (see run_stages).
STAGES = ("register", "track", "subject", "solve", "record", "export")
Bones = tuple[tuple[str, str], ...]  # pairs of point names drawn as lines in the recording
# register's advice without tracks (sfm.register_subject.TRACK_ADVICE), in `run`'s own options
RUN_TRACK_ADVICE = (
    "label the subject on a few frames (dynrecon label WS --videos VIDEO...; run then tracks WS/labels.csv), or give "
    "a detector's tracks (--tracks FILE, from dynrecon import-tracks), and run again"
)


__all__ = [
    "REGISTER_DIR",
    "STAGES",
    "STATE_NAME",
    "SUBJECT_DIR",
    "Bones",
    "PipelineOptions",
    "PipelineResult",
    "Registration",
    "Similarity",
    "StageRun",
    "Stages",
    "State",
    "Tracker",
    "align_to_truth",
    "default_register",
    "export_points",
    "export_rate",
    "file_hash",
    "import_registration",
    "inputs_key",
    "run",
    "run_stages",
    "score_against_truth",
    "similarity_to_truth",
    "triggered_rate",
]


def default_register() -> RegisterOptions:
    # No tracks exist when registering (see the module docstring): localize every frame.
    return RegisterOptions(localize=Localize.ALL)


@dataclass(kw_only=True)
class PipelineOptions:
    register: RegisterOptions = field(default_factory=default_register)
    track: TrackOptions = field(default_factory=TrackOptions)
    solve: SolveOptions = field(default_factory=lambda: SolveOptions(recording=None))
    labels: Path | None = None  # clicks to track (default: WS/labels.csv when it exists)
    tracks: Path | None = None  # or ready 2D tracks (detector output, ...): no track stage
    skeleton: Path | None = None  # skeleton JSON for the recording (points and connections)
    calibration: Path | None = None  # a lab calibration (`dynrecon import-calibration`'s files): replaces SfM
    calibration_options: ImportCalibrationOptions = field(default_factory=ImportCalibrationOptions)  # format, units
    # unit label written into TRC/C3D; None: the world's own (metres from a calibration, --scale or --board), else mm
    # (an SfM world's scale is arbitrary, which register says)
    units: str | None = None
    force: bool = False  # redo every stage

    def background_register(self, *, labels: bool = False) -> RegisterOptions:
        """The `register` stage's options: without tracks, so that new tracks never force a new registration.
        Markers in view are tracks register finds itself, unless the user's tracks come later (`labels` in WS,
        --tracks, the board's corners): then the subject stage registers with those, as the user asked."""
        coming = labels or self.tracks is not None or self.register.board is not None
        return dataclasses.replace(
            self.register, tracks=None, board=None, find_markers=self.register.find_markers and not coming
        )

    def subject_register(self, tracks: Path) -> RegisterOptions:
        """The `subject` stage's options: the registration again, with the subject's tracks."""
        return dataclasses.replace(self.register, tracks=tracks)

    def solve_options(self, bones: Bones) -> SolveOptions:
        """The `solve` stage's options: no recording (the `record` stage draws it, with the videos)."""
        return dataclasses.replace(self.solve, recording=None, skeleton=bones)


@dataclass(kw_only=True)
class StageRun:
    name: str
    skipped: bool
    seconds: float


@dataclass(kw_only=True)
class PipelineResult:
    workspace: Path
    stages: list[StageRun]
    order_source: OrderSource | None = None
    next_step: str | None = None  # what the user does next when the run stopped short (registration only)

    def seconds(self, name: str) -> float:
        return next((s.seconds for s in self.stages if s.name == name), 0.0)


# ----------------------------------------------------------------------------------------------------------
# The pipeline


def _check(videos: list[Path], options: PipelineOptions) -> None:
    for video in videos:
        if not video.is_file():
            raise InputError(video, "video not found", fix="give the paths of existing video files")
    if options.labels is not None and options.tracks is not None:
        raise InputError(
            options.tracks,
            "both labels and tracks were given",
            fix="give --labels (to track them) or --tracks (ready 2D tracks), not both",
        )
    for given in (options.labels, options.tracks, options.skeleton):
        if given is not None and not given.is_file():
            raise InputError(given, "is a folder: a file was expected" if given.is_dir() else "file not found")
    # the user's own file is named in its errors, not the copy in WS that the stages read
    names = {video.stem for video in videos}
    points: set[str] | None = None
    named: list[str] = []  # the videos the user's tracks or labels give pixels of
    if options.tracks is not None:
        tracks = matched_to_videos(read_tracks(options.tracks), names)  # back.mp4 for back: what register reads
        named = tracks.video_names()
        _check_video_names(options.tracks, named, names)
        points = set(tracks.point)
    if options.labels is not None:
        labels = read_labels(options.labels)
        named = list(dict.fromkeys(key[0] for key in labels))
        _check_video_names(options.labels, named, names)
        points = {key[2] for key in labels}
    if options.register.scale is not None and points is not None:
        check_scale_points(options.register.scale, points, options.tracks or options.labels)
    given = options.tracks or options.labels
    if given is not None:
        _say_rotated([video for video in videos if video.stem in named], given)
    if options.calibration is not None:
        _check_calibration(options.calibration, options.calibration_options, options.register)
    options.register.check()
    if options.units is not None:  # before the solve, not at its export
        check_units(options.units)
    if options.register.board is not None:
        read_charuco_board(options.register.board)  # a bad board file fails before any stage runs
    if options.skeleton is not None:
        read_skeleton(options.skeleton)  # ... and so does a bad skeleton, read only at the recording


def _say_rotated(videos: list[Path], given: Path) -> None:
    """A warning per video with a rotation flag: the pixels of the user's labels or tracks must be upright ones."""
    for video in videos:
        try:
            capture = video_io.open_video(video)
        except InputError:
            continue  # an unreadable video is left out by register, which names it
        try:
            degrees = video_io.rotation(capture)
        finally:
            capture.release()
        if degrees:
            log.warning(video_io.rotated_pixels_message(video.stem, degrees, given))


def _check_video_names(path: Path, used: list[str], videos: set[str]) -> None:
    unknown = [name for name in used if name not in videos]
    if unknown:
        raise InputError(
            path,
            f"video(s) {', '.join(unknown[:5])} are not among the videos given ({', '.join(sorted(videos)[:8])})",
            fix="name the rows after the video files (file name without extension), or give those videos",
        )


def _option_files(register: RegisterOptions) -> dict[str, Path]:
    """The files a registration option names, so that editing one reruns the stage that reads it."""
    named = {"intrinsics": register.intrinsics, "board": register.board}
    return {key: path for key, path in named.items() if path is not None}


def _check_calibration(calibration: Path, imported: ImportCalibrationOptions, register: RegisterOptions) -> None:
    """A calibration that exists, can be read and has a known format, without the registration options it
    replaces: checked before any stage runs."""
    fix = (
        "give a calibration that `dynrecon import-calibration` reads (.toml, .qca.txt, .qca, .xml, cameras.json, "
        "a Label3D/DANNCE .mat, DLTdv/easyWand/Argus DLT coefficients)"
    )
    if not calibration.exists():
        raise InputError(calibration, "calibration file not found", fix=fix)
    if not calibration.is_file():
        raise InputError(
            calibration,
            "is not a file: a calibration file was expected",
            fix="a folder of DANNCE's cam*_params.mat: `dynrecon import-calibration FOLDER VIDEO... --out CAL`, then "
            "--calibration CAL/cameras.json",
        )
    try:
        with calibration.open("rb"):
            pass
    except OSError as error:
        raise InputError(
            calibration, f"cannot read the calibration file ({error.strerror or error})", fix=fix
        ) from None
    if register.intrinsics is not None or register.scale is not None or register.board is not None:
        raise InputError(
            calibration,
            "a calibration gives the cameras: --intrinsics, --scale and --board (registration options) do not apply",
            fix="leave out --intrinsics, --scale and --board, or the calibration",
        )
    lower = calibration.name.lower()
    # sfm.calibration's own rule for the format; its message would name import-calibration's --format.
    known = lower.endswith((".toml", ".xml", ".json", ".mat")) or ".qca" in lower or is_dlt(calibration)
    if imported.format is CalibrationFormat.AUTO and not known:
        raise InputError(
            calibration,
            "cannot tell the calibration format from the name",
            fix="pass --calibration-format qca, toml, json, dannce or dlt, or name the file .toml / .qca.txt / .qca / "
            ".xml / .json / .mat / *_dltCoefs.csv",
        )
    if imported.profile is not None and not imported.profile.is_file():
        raise InputError(imported.profile, "camera profile not found", fix="give the DLT calibration's *_profile.txt")


def _solve_posed_videos(cameras_path: Path, tracks_path: Path, out: Path, options: SolveOptions) -> None:
    """The solve of the tracks of the videos registration posed: a video it could not pose (its register report
    says why) is left out of the solve with a warning, not an error, so that the others are still reconstructed."""
    cameras = read_cameras(cameras_path)
    tracks = matched_to_videos(read_tracks(tracks_path), [v.name for v in cameras.videos])
    posed = {v.name for v in cameras.videos if v.frames}
    left_out = sorted(set(tracks.video) - posed)
    given = {v.name for v in cameras.videos}
    absent = [name for name in left_out if name not in given]  # a video dropped from this run
    if absent:
        log.warning(
            "%s: video(s) %s have tracks but are not among this run's videos: their tracks are left out of the solve",
            tracks_path,
            ", ".join(absent),
        )
    unposed = [name for name in left_out if name in given]
    if unposed:
        log.warning(
            "%s: video(s) %s have tracks but registration posed none of their frames (%s says why): their tracks "
            "are left out of the solve",
            tracks_path,
            ", ".join(unposed),
            cameras_path.parent / "register_report.json",
        )
    if left_out:
        tracks = tracks.take(np.flatnonzero([v in posed for v in tracks.video]))
    solve(cameras_path, tracks, options).write(out)  # the path: report.json names its inputs


def _copy_into(source: Path, target: Path) -> None:
    """Copy a user's file into the workspace unless it already is that file; a different file already there (the
    labeling page's clicks) is kept beside it, with a warning, never overwritten."""
    if source.resolve() == target.resolve():
        return
    if target.is_file() and target.read_bytes() != source.read_bytes():
        keep_aside(target, f"differed from {source}")
    with atomic_open(target, "wb") as out, source.open("rb") as given:  # never a half-copied file (a full disk)
        shutil.copyfileobj(given, out)


def run(videos: Sequence[str | Path], out_dir: str | Path, options: PipelineOptions | None = None) -> Path:
    """Run every stage that is not up to date; returns WS (see `run_stages` for the per-stage details)."""
    return run_stages(videos, out_dir, options).workspace


def run_stages(
    videos: Sequence[str | Path], out_dir: str | Path, options: PipelineOptions | None = None
) -> PipelineResult:
    """Run every stage that is not up to date, in order (the module docstring says which run when)."""
    stages = Stages(videos, out_dir, options)
    background_failed = stages.register()
    registration = stages.finish(background_failed)
    if registration is None:
        return stages.result
    ws = stages.ws
    stages.result.order_source = _order(ws, registration.cameras)[1]
    ran = ", ".join(f"{s.name} {s.seconds:.1f} s" for s in stages.result.stages if not s.skipped) or "nothing to redo"
    log.info("pipeline done (%s); open the recording with: rerun %s", ran, ws / "recording.rrd")
    return stages.result


@dataclass(kw_only=True)
class Registration:
    """The cameras the later stages use: the background registration's (or calibration's), or the subject path's."""

    cameras: Path
    background: Path

    @classmethod
    def in_folder(cls, folder: Path) -> Registration:
        return cls(cameras=folder / "cameras.json", background=folder / "background.ply")


Tracker = Callable[[Path], object]  # writes the 2D tracks of the labels into the given tracks.csv
Registrar = Callable[[list[Path], Path, RegisterOptions], object]  # registers the videos into the given folder


class Stages:
    """The pipeline's stages on one workspace, one method each, in the order `run_stages` calls them. Each runs, or
    is skipped when `WS/pipeline.json` says its inputs (file contents, options) and outputs are those of its last run.

    Any process may run any stage on the same workspace (a shared filesystem): the state is in WS's files, and each
    method takes and returns paths. `result` lists what this object ran or skipped.

        stages = Stages(videos, ws, options)  # the arguments of run_stages
        failed = stages.register()  # cameras (SfM, or options.calibration imported)
        stages.finish(failed)  # track, subject, solve, record, export (or stages.track() ... stages.export(...))
    """

    def __init__(
        self, videos: Sequence[str | Path], workspace: str | Path, options: PipelineOptions | None = None
    ) -> None:
        """Checks the inputs (a one-line InputError, before anything is written), then makes WS."""
        self.options = options or PipelineOptions()
        self.videos = [Path(v) for v in videos]
        _check(self.videos, self.options)
        self.ws = require_writable(workspace)  # a file in the way is a one-line error, not a traceback
        self.ws.mkdir(parents=True, exist_ok=True)
        given_tracks = self.options.tracks
        if given_tracks is not None and given_tracks.resolve().is_relative_to(self.ws.resolve()):
            # a file of this workspace (register's marker_tracks.csv) that a stage may rewrite or remove: its copy
            # in WS/tracks.csv, made before any stage runs, is the input
            _copy_into(given_tracks, self.ws / "tracks.csv")
            self.options = dataclasses.replace(self.options, tracks=self.ws / "tracks.csv")
        self.video_files = {f"video:{p.stem}": p for p in self.videos}
        self.state = State(self.ws)
        self.result = PipelineResult(workspace=self.ws, stages=[])
        # The clicks to track: the given labels, else those the labeling page saved in WS.
        given = self.options.labels
        self.labels = given or (self.ws / "labels.csv" if (self.ws / "labels.csv").is_file() else None)

    @property
    def bones(self) -> Bones:
        """The skeleton's connections, drawn in the recording."""
        return _bones(self.options.skeleton)

    def run(
        self, name: str, files: dict[str, Path], settings: Any, outputs: list[Path], work: Callable[[], object]
    ) -> None:
        """Run `work` unless `files` (contents) and `settings` are those of the last run and `outputs` are intact."""
        number = STAGES.index(name) + 1
        key = inputs_key(files, settings)
        if not self.options.force and self.state.up_to_date(name, key, self.ws):
            log.info("[%d/%d] %s: up to date, skipped", number, len(STAGES), name)
            self.result.stages.append(StageRun(name=name, skipped=True, seconds=0.0))
            return
        log.info("[%d/%d] %s ...", number, len(STAGES), name)
        self.state.forget(name)  # a stage that fails half-way must not look done
        started = time.perf_counter()
        work()
        seconds = time.perf_counter() - started
        missing = [p for p in outputs if not p.is_file()]
        if missing:
            raise InputError(missing[0], f"stage {name} did not write this file")
        self.state.record(name, key, outputs, self.ws, seconds)
        log.info("[%d/%d] %s: done in %.1f s", number, len(STAGES), name, seconds)
        self.result.stages.append(StageRun(name=name, skipped=False, seconds=seconds))

    def register(self, registrar: Registrar | None = None) -> RegistrationError | None:
        """The `register` stage into WS/register/: SfM, or the import of `options.calibration`. An SfM failure is
        returned, not raised, when tracks will come to pose the static videos from the subject (`subject`).
        `registrar(videos, folder, options)` replaces SfM (the batch finishes its per-video tasks' registration);
        the stage's hash is the same."""
        options = self.options
        folder = self.ws / REGISTER_DIR
        files, settings, outputs = self._register_inputs()
        calibration = options.calibration
        # what the stage last wrote, read before `run` forgets the stage (it does so before the work)
        written = self.state.output_hash("register", folder / "cameras.json", self.ws)
        if calibration is not None:
            imported = options.calibration_options
            self.run(
                "register",
                files,
                settings,
                outputs,
                lambda: self._unrecorded_aside(
                    folder, written, lambda: import_registration(calibration, self.videos, folder, imported)
                ),
            )
            return None
        register_options = self.background_options()
        sfm = registrar or _register
        key = inputs_key(files, settings)
        try:
            failure = None if options.force else self.state.failed_before("register", key, self.ws)
            # SfM would fail again on the same inputs: minutes of mapping for the same answer (a record edited by
            # hand that lacks a field is redone)
            if failure is not None and {"what", "reason", "report"} <= failure.keys():
                log.info("[1/%d] register: failed on these inputs before (pipeline.json), not redone", len(STAGES))
                self.result.stages.append(StageRun(name="register", skipped=True, seconds=0.0))
                raise RegistrationError.of(failure["what"], failure["reason"], self.ws / failure["report"])
            try:
                self.run(
                    "register",
                    files,
                    settings,
                    outputs,
                    lambda: self._unrecorded_aside(folder, written, lambda: sfm(self.videos, folder, register_options)),
                )
            except RegistrationError as failed:
                ws = self.ws.resolve()
                report = failed.report.resolve() if failed.report is not None else None
                if report is not None and report.is_file() and failed.reason and report.is_relative_to(ws):
                    said = {"what": failed.what, "reason": failed.reason, "report": str(report.relative_to(ws))}
                    self.state.record_failure("register", key, said, [report], ws)  # its own words and report
                raise
        except RegistrationError as error:
            tracks_coming = options.tracks is not None or self.labels is not None or options.register.board is not None
            if not tracks_coming and not (self.ws / "tracks.csv").is_file():
                error = error.advising(TRACK_ADVICE, RUN_TRACK_ADVICE)
                hint = board_hint(self.videos) if options.register.find_markers else None
                raise (error.with_hint(hint) if hint else error) from None
            log.warning(
                "background SfM: %s (%s says why); the static videos will be posed from the subject's tracks "
                "after tracking (the subject stage)",
                error.what,
                error.report or "register_report.json",
            )
            return error
        return None

    def background_options(self) -> RegisterOptions:
        """The `register` stage's options for this workspace (markers only where no labels are in it)."""
        return self.options.background_register(labels=self.labels is not None)

    def register_up_to_date(self) -> bool:
        """Whether `register()` would skip its stage (the batch's per-video registration tasks skip then too)."""
        files, settings, _ = self._register_inputs()
        return not self.options.force and self.state.up_to_date("register", inputs_key(files, settings), self.ws)

    def _register_inputs(self) -> tuple[dict[str, Path], dict[str, Any], list[Path]]:
        """The `register` stage's input files, settings and outputs (its hash in pipeline.json)."""
        options = self.options
        registration = Registration.in_folder(self.ws / REGISTER_DIR)
        outputs = [registration.cameras, registration.background]
        names = [p.stem for p in self.videos]
        if options.calibration is not None:
            settings = {"calibration": options.calibration.name, "import": options.calibration_options, "videos": names}
            files = {**self.video_files, "calibration": options.calibration}
            if options.calibration_options.profile is not None:  # its contents, not only its name
                files["profile"] = options.calibration_options.profile
            return files, settings, outputs
        # the files its options name, by content: an --intrinsics file edited in place registers again
        files = {**self.video_files, **_option_files(self.background_options())}
        return files, {"register": self.background_options(), "videos": names}, outputs

    def track(self, tracker: Tracker | None = None) -> Path | None:
        """The `track` stage (labels -> WS/tracks.csv), or a copy of the given tracks; None when there are neither.
        `tracker` replaces the tracker (the batch merges per-video files); the stage's hash is the same."""
        ws, options, labels = self.ws, self.options, self.labels
        tracks_path = ws / "tracks.csv"
        if options.tracks is not None:
            _copy_into(options.tracks, tracks_path)
            self.state.forget("track")
        elif labels is not None:
            _copy_into(labels, ws / "labels.csv")
            write = tracker or (lambda out: _track(ws, out, self.videos, options.track))
            self.run(
                "track",
                {**self.video_files, "labels": ws / "labels.csv"},
                {"track": options.track},
                [tracks_path],
                lambda: write(tracks_path),
            )
        elif options.register.board is not None and self._tracks_are_ours(tracks_path):
            # the board's corners are the tracks (a tracks.csv the user put in WS is theirs: kept)
            board = options.register.board
            self.run(
                "track",
                {**self.video_files, "board": board},
                {"board": board.name},
                [tracks_path],
                lambda: board_tracks(self.videos, board, self.ws),
            )
        elif not tracks_path.is_file():
            self.result.next_step = (
                f"no labels and no tracks: registration only. Label the points with `dynrecon label {ws} "
                "--videos ...`, then run this command again"
            )
            found = ws / REGISTER_DIR / MARKER_TRACKS
            if found.is_file():  # the markers register posed the cameras from may be the subject itself
                # a copy outside register/, which the register stage rewrites when it runs again (without markers);
                # a user's edited copy from an earlier run is kept aside, not overwritten
                markers = ws / MARKER_TRACKS
                _copy_into(found, markers)
                self.result.next_step += (
                    f"; or, to reconstruct the markers in view, run it again with --tracks {markers}"
                )
            log.info("%s", self.result.next_step)
            return None
        if not tracks_path.is_file():
            raise InputError(tracks_path, "no 2D tracks were written", fix="check the labels")
        return tracks_path

    def _unrecorded_aside(self, folder: Path, written: str | None, write: Callable[[], object]) -> None:
        """`write` (the register stage's work) after a `folder`/cameras.json it did not write (its hash is not
        `written`, the stage's last record: a user's import-calibration into WS/register/) is kept aside, not
        replaced unseen."""
        cameras = folder / "cameras.json"
        if cameras.is_file() and (written is None or file_hash(cameras) != written):
            keep_aside(cameras, "was not written by the register stage, which writes it now")
        write()

    def _tracks_are_ours(self, tracks_path: Path) -> bool:
        """Whether WS/tracks.csv may be (re)written by the track stage: missing, or the one it wrote last."""
        if not tracks_path.is_file():
            return True
        recorded = self.state.output_hash("track", tracks_path, self.ws)
        return recorded is not None and file_hash(tracks_path) == recorded

    def subject(self, tracks: Path, background_failed: RegistrationError | None = None) -> Registration:
        """The background's cameras, or, where it failed or left static videos out, the `subject` stage's
        (registered again with the subject's tracks, into WS/register_subject/)."""
        background = self.ws / REGISTER_DIR
        track_set = read_tracks(tracks)
        people = per_video_people(track_set) is not None
        if background_failed is None and self.options.calibration is not None and people:
            return self._people_on_calibration(background, tracks, track_set)
        if background_failed is None and not _static_left_out(background / "register_report.json"):
            if people:
                # which person of one video is which of another: registration finds it from the tracks
                log.info("the tracks number people per video: registering again with them, which matches the people")
            else:
                # the background registered without tracks: its static poses are checked against them now
                refuted = refuted_in_folder(background, track_set, self.videos, self.options.register.max_offset)
                if not refuted:
                    return Registration.in_folder(background)
                log.warning(
                    "the subject's tracks refute the background's poses of %s (%s): registering again with the tracks",
                    ", ".join(sorted(refuted)),
                    next(iter(refuted.values())),
                )
        folder = self.ws / SUBJECT_DIR
        registration = Registration.in_folder(folder)
        subject_options = self.options.subject_register(tracks)
        self.run(
            "subject",
            {**self.video_files, "tracks": tracks, **_option_files(subject_options)},
            {"register": subject_options, "videos": [p.stem for p in self.videos]},
            [registration.cameras, registration.background],
            lambda: _register(self.videos, folder, subject_options),
        )
        return registration

    def _people_on_calibration(self, background: Path, tracks: Path, track_set: Tracks) -> Registration:
        """The calibration's cameras with each video's people map (the tracks number people per video), into
        WS/register_subject/: the `subject` stage of a calibrated rig."""
        folder = self.ws / SUBJECT_DIR
        registration = Registration.in_folder(folder)

        def match() -> None:
            folder.mkdir(parents=True, exist_ok=True)
            people_on_cameras(background / "cameras.json", track_set, self.videos, folder)
            shutil.copyfile(background / "background.ply", registration.background)

        files = {"cameras": background / "cameras.json", "tracks": tracks}
        self.run("subject", files, {"people": True}, [registration.cameras, registration.background], match)
        return registration

    def solve(self, registration: Registration, tracks: Path) -> None:
        """The `solve` stage: WS/points3d.csv, sequencing.json, report.json."""
        ws = self.ws
        solve_options = self.options.solve_options(self.bones)
        solved = [ws / "points3d.csv", ws / "sequencing.json", ws / "report.json"]
        self.run(
            "solve",
            {"cameras": registration.cameras, "tracks": tracks},
            {"solve": solve_options},
            solved,
            lambda: _solve_posed_videos(registration.cameras, tracks, ws, solve_options),
        )

    def record(self, registration: Registration, tracks: Path) -> None:
        """The `record` stage: WS/recording.rrd."""
        ws, bones = self.ws, self.bones
        files = {
            **self.video_files,
            "cameras": registration.cameras,
            "background": registration.background,
            "tracks": tracks,
            "points": ws / "points3d.csv",
            "report": ws / "report.json",
            "sequencing": ws / "sequencing.json",
        }
        self.run(
            "record",
            files,
            {"skeleton": bones},
            [ws / "recording.rrd"],
            lambda: _record(ws, registration.cameras, registration.background, tracks, self.videos, bones),
        )

    def export(self, registration: Registration) -> None:
        """The `export` stage: WS/points.trc, points.c3d."""
        ws, units = self.ws, self.options.units or _world_units(self.options, registration)
        files = {"cameras": registration.cameras, "points": ws / "points3d.csv", "sequencing": ws / "sequencing.json"}
        self.run(
            "export",
            files,
            {"units": units},
            [ws / "points.trc", ws / "points.c3d"],
            lambda: export_points(ws, registration.cameras, units),
        )

    def finish(
        self, background_failed: RegistrationError | None = None, *, tracker: Tracker | None = None
    ) -> Registration | None:
        """Every stage after `register`, in order: track, subject, solve, record, export. Returns the cameras the
        results were solved with, or None when there are no labels or tracks (registration only)."""
        tracks = self.track(tracker)
        if tracks is None:
            return None
        registration = self.subject(tracks, background_failed)
        self.solve(registration, tracks)
        self.record(registration, tracks)
        self.export(registration)
        return registration


def _bones(skeleton_path: Path | None) -> Bones:
    """The connections of the skeleton file, drawn as bones in the recording; none without a file."""
    if skeleton_path is None:
        return ()
    return tuple((a, b) for a, b in read_skeleton(skeleton_path).connections)


# ----------------------------------------------------------------------------------------------------------
# Stage bodies


def _register(videos: list[Path], register_dir: Path, options: RegisterOptions) -> None:
    given: list[str | Path] = list(videos)
    register_run(given, register_dir, options)


def import_registration(
    calibration: Path, videos: Sequence[Path], folder: Path, options: ImportCalibrationOptions | None = None
) -> Path:
    """A calibrated (static) rig's registration folder, as `dynrecon import-calibration` writes it: cameras.json
    (every decoded frame, its camera's fixed pose) and an empty background.ply (there is no SfM model); returns
    cameras.json."""
    cameras = import_calibration(calibration, list(videos), folder, options)
    write_ply(folder / "background.ply", np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    # An earlier SfM run's report would describe other cameras (and could send the subject stage off).
    (folder / "register_report.json").unlink(missing_ok=True)
    return cameras


def _static_left_out(report_path: Path) -> bool:
    """Whether the background registration left a static video without a pose (its report says so)."""
    try:
        report = json.loads(report_path.read_text(encoding="utf-8"))
        return any(v.get("camera") == "static" and v.get("posed_by") == "none" for v in report.get("videos", []))
    except (OSError, ValueError, AttributeError, TypeError):
        return False


def _track(ws: Path, tracks_path: Path, videos: list[Path], options: TrackOptions) -> None:
    tracks_path.unlink(missing_ok=True)  # the tracker keeps rows of untracked videos: start clean
    track_run(ws, tracks_path, options, videos={p.stem: p for p in videos})


def _residual(ws: Path, keys: list[tuple[str, int]]) -> np.ndarray | None:
    try:
        per_frame = json.loads((ws / "report.json").read_text(encoding="utf-8"))["residual"]["per_frame"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    # null: a frame that observes no point (the solver leaves it out): a gap in the plot
    by_key = {(e["video"], int(e["frame"])): float_or_nan(e["residual"]) for e in per_frame}
    values = [by_key.get(key) for key in keys]
    return None if any(v is None for v in values) else np.array(values, dtype=float)


def _order(ws: Path, cameras_path: Path) -> tuple[np.ndarray, OrderSource]:
    points = read_points(ws / "points3d.csv")
    cameras = read_cameras(cameras_path)
    return global_order(points, cameras, read_sequencing(ws / "sequencing.json"))


def triggered_rate(times: np.ndarray, videos: list[str]) -> float | None:
    """The fastest video's rate where the videos' frames coincide in global time (`times` (F,)): a triggered rig,
    whose interleaved export would repeat each instant (a 120 Hz rig exported at 240 Hz); None where they interleave.
    Coincide: nine frames in ten have another video's frame within a tenth of the fastest video's frame gap."""
    names, index = np.unique(np.asarray(videos), return_inverse=True)
    known = np.isfinite(times)
    own = {v: np.sort(times[known & (index == v)]) for v in range(len(names)) if np.any(known & (index == v))}
    periods = frame_periods(times, index, len(names))
    if len(own) < 2 or not np.isfinite(periods).any():
        return None
    tolerance = 0.1 * float(np.nanmin(periods))
    together = 0
    for v, mine in own.items():
        others = np.sort(np.concatenate([t for u, t in own.items() if u != v]))
        together += int(np.sum(nearest_gap(others, mine) <= tolerance))
    # rounded: a rate from decoder times (799.9999999999993 Hz) is written into the exports' headers
    return round(1.0 / float(np.nanmin(periods)), 6) if together >= 0.9 * int(known.sum()) else None


def export_rate(cameras: CameraSet, frames: int, videos: set[str] | None = None) -> float:
    """Rows per second of an interleaved export: the sum of the frame rates of `videos` (default: every video of
    `cameras`; nominal, or measured from decoder times: the median frame step, which gaps of dropped or untracked
    frames do not lengthen); 30 Hz per video when neither is known."""
    total = 0.0
    for video in cameras.videos:
        if videos is not None and video.name not in videos:
            continue  # left out of the solve: no rows
        times = np.array([f.time for f in video.frames if f.time is not None], dtype=float)
        period = frame_periods(times, np.zeros(len(times), dtype=np.int64), 1)[0]
        if video.fps:
            total += float(video.fps)
        elif np.isfinite(period):
            total += 1.0 / float(period)
        else:
            total += 30.0
    return total if total > 0 else 30.0 * max(1, frames)


def _record(
    ws: Path, cameras_path: Path, background_path: Path, tracks_path: Path, videos: list[Path], bones: Bones
) -> None:
    cameras = read_cameras(cameras_path)
    points = read_points(ws / "points3d.csv")
    sequencing = read_sequencing(ws / "sequencing.json")
    order, source = global_order(points, cameras, sequencing)
    if source is OrderSource.CLOCKS:
        times = clock_times(points, sequencing)
    else:
        times = frame_times(points, cameras) if source is OrderSource.TIME else None
    if times is None:
        times = np.empty(points.num_frames)
        times[order] = np.arange(points.num_frames) / export_rate(cameras, points.num_frames, set(points.videos))
    xyz, rgb = read_ply(background_path)
    keys = [(v, int(f)) for v, f in zip(points.videos, points.frames, strict=True)]
    known = set(points.point_names)
    skeleton = [(a, b) for a, b in bones if a in known and b in known]
    other = [p.name for p in videos if p.suffix.lower() != ".mp4"]
    if other:  # rerun plays videos in .mp4 only (it refuses QuickTime's .mov, whatever the codec)
        log.info("recording: %s not embedded (rerun plays .mp4 files; remux with ffmpeg -c copy)", ", ".join(other))
    write_recording(
        ws / "recording.rrd",
        cameras=cameras,
        points=points,
        tracks=read_tracks(tracks_path),
        skeleton=skeleton or None,
        residual=_residual(ws, keys),
        global_time=times,
        background=BackgroundCloud(xyz=xyz, colors=rgb),
        video_files={p.stem: p for p in videos if p.suffix.lower() == ".mp4"},
    )


def _world_units(options: PipelineOptions, registration: Registration) -> str:
    """The unit of the cameras' world: a calibration's (metres times its --scale), the subject path's metres (from
    --scale or --board), else mm as a label (an SfM world has an arbitrary scale)."""
    if options.calibration is not None:
        named = {1.0: "m", 100.0: "cm", 1000.0: "mm"}
        return named.get(float(options.calibration_options.scale), "mm")
    return "m" if registered_in_metres(registration.cameras, written_with=False) else "mm"


def registered_in_metres(cameras_path: Path, *, written_with: bool = True) -> bool | None:
    """Whether `register` gave the cameras of `cameras_path` metres (`--scale`, `--board`): its
    register_report.json beside them says so; False where it gave an arbitrary scale (an SfM world, the subject's
    tracks alone); None where there is no report, or with `written_with` where the report is older than the
    cameras (a calibration imported over a registration; a pipeline's own workspace need not check)."""
    report = cameras_path.parent / "register_report.json"
    try:
        if written_with and report.stat().st_mtime < cameras_path.stat().st_mtime - 2.0:  # register writes it last
            return None
        subject = json.loads(report.read_text(encoding="utf-8")).get("subject") or {}
    except (OSError, ValueError, AttributeError):
        return None
    return subject.get("units") == "m"


def export_points(ws: Path, cameras_path: Path, units: str) -> None:
    """WS/points.trc and points.c3d from a solve's WS/points3d.csv and sequencing.json on `cameras_path`: the
    `export` stage, and `dynrecon export` (a solve without videos, e.g. a calibration and tracks shared without
    them). `units`: the cameras' world unit, the exports' label."""
    points = measured_only(read_points(ws / "points3d.csv"))  # once here: the writers then find nothing to say
    cameras = read_cameras(cameras_path)
    sequencing = read_sequencing(ws / "sequencing.json")
    order, source = global_order(points, cameras, sequencing)
    rate = export_rate(cameras, points.num_frames, set(points.videos))
    times = clock_times(points, sequencing) if source is OrderSource.CLOCKS else None
    if times is not None:
        rate = triggered_rate(times, points.videos) or rate
    log.info(
        "export: %s at %.1f Hz, ordered by %s",
        "resampled on the recovered clock" if times is not None else f"{len(order)} rows",
        rate,
        source.value,
    )
    write_trc_export(points, order, rate, ws / "points.trc", units=units, times=times)
    if times is not None:
        write_c3d_export(points, order, rate, ws / "points.c3d", units=units, times=times, note=clock_note(sequencing))
    else:
        write_c3d_export(points, order, rate, ws / "points.c3d", units=units)


def score_against_truth(ws: Path, truth_path: Path, truth_cameras_path: Path) -> ReconstructionAccuracy:
    """`dynrecon.truth.score_points` of a `dynrecon run` workspace: its points3d.csv on its registered cameras."""
    return score_points(ws / "points3d.csv", ws / REGISTER_DIR / "cameras.json", truth_path, truth_cameras_path)
