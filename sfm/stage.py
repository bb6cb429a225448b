"""`sfm.register` (`run` here): a pose and intrinsics for every frame of every video, in one world frame.

Stages: probe videos -> test each camera for motion (`sfm.static`) -> SfM images: a static video sends one
background image (temporal median), a moving one sampled frames (+ masks) -> SIFT (one camera per video) ->
matching of sequential pairs within a video and of every keyframe / background image across videos -> mapping
(incremental or global), keep the largest model -> a static video's frames take its background image's pose, a
moving video's other frames are posed by PnP against the model -> static videos the background left out are
posed from the moving subject's 2D tracks (`sfm.register_subject`, anchored on the videos the background posed)
-> cameras.json, background.ply, register_report.json (which path posed each video, and why).
pycolmap stages run in child processes (`sfm.isolated`) so that a fatal COLMAP error is a clear message.
"""

from __future__ import annotations

import contextlib
import dataclasses
import filecmp
import json
import logging
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import pycolmap
from tqdm import tqdm

from dynrecon import video_io
from dynrecon.atomic import require_writable
from dynrecon.beside import one_core
from dynrecon.errors import DynreconError, InputError
from dynrecon.names import first_repeated
from sfm import colmap_steps
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, check_plausible, read_cameras, write_cameras
from sfm.export import write_ply
from sfm.intrinsics import intrinsics_sizes, known_intrinsics, read_intrinsics_file
from sfm.isolated import run_isolated
from sfm.layout import Layout
from sfm.masks import check_mask_folder
from sfm.options import ALL_CORES, CameraMotion, Localize, Mapper, RegisterOptions, SubjectPath, declared_offsets
from sfm.pairs import build_pairs, word_vectors
from sfm.path_check import drop_spikes
from sfm.per_video import (
    capture_facts,
    clear_outputs,
    collected,
    extract_videos,
    localize_video,
    merge_features,
    prepare_video,
    timed,
    wanted_frames,
)
from sfm.plan import FramePose, VideoPlan
from sfm.plan_io import StepNotes, read_poses, read_prepared
from sfm.register_check import (
    TWO_VIEWS_WHY,
    background_left,
    check_background,
    refuse_two_view_focals,
    unpose_background,
)
from sfm.register_markers import MARKER_TRACKS, tracks_from_markers
from sfm.register_people import match_people
from sfm.register_subject import pose_from_subject
from sfm.report import write_report
from sfm.resume import StepLog, input_key
from sfm.subject.agreement import no_lens
from sfm.video import ProbedVideo, probe_video, video_name
from sfm.video_standin import stand_in_videos, with_size
from tracking.charuco import charuco_tracks, read_charuco_board
from tracking.tracks import Tracks, matched_to_videos, read_tracks, write_tracks

log = logging.getLogger(__name__)

Results = dict[str, dict[int, FramePose]]  # video name -> frame -> its outcome
MERGE_STEP = "merge"
# A background model needs this many 3D points to be kept: fewer pose its images on next to nothing, and a frame's
# localization needs `RegisterOptions.min_inliers` (30) 2D-3D matches
MIN_MODEL_POINTS = 30
_wanted_frames = wanted_frames  # its older name (tests)


class RegistrationError(DynreconError):
    """SfM could not put at least two videos into one model. `what`: how many videos were posed; `report`: the
    register_report.json that says why."""

    def __init__(self, message: str, *, what: str = "", report: Path | None = None, reason: str = "") -> None:
        super().__init__(message)
        self.what = what or message
        self.report = report
        self.reason = reason  # why, and what to do (the message's middle part)

    @classmethod
    def of(cls, what: str, reason: str, report: Path) -> RegistrationError:
        return cls(
            f"{what}; cameras.json not written: {reason}. Details: {report}", what=what, report=report, reason=reason
        )

    def advising(self, advice: str, instead: str) -> RegistrationError:
        """The same failure with `advice` in its reason replaced by `instead` (another command's own options)."""
        if advice not in self.reason or self.report is None:
            return self
        return RegistrationError.of(self.what, self.reason.replace(advice, instead), self.report)

    def with_hint(self, hint: str) -> RegistrationError:
        """The same failure with `hint` added to what to do."""
        if not self.reason or self.report is None:  # a message carried as text (the batch's tasks)
            return RegistrationError(f"{self}; {hint}", what=self.what, report=self.report)
        return RegistrationError.of(self.what, f"{self.reason}; {hint}", self.report)


MIN_SCALE_M, MAX_SCALE_M = 1e-6, 1e6  # --scale distances outside this are a typo, not a subject


def run(videos: Sequence[str | Path], out_dir: str | Path, options: RegisterOptions | None = None) -> Path:
    """Register `videos` into one world frame; returns the path of the written `cameras.json`.

    The per-video steps (`sfm.per_video`) run one video after the other here; `dynrecon batch` runs the same
    functions as parallel tasks. With `num_threads` 1 nothing runs beside the caller either (`one_core`)."""
    options = options or RegisterOptions()
    with one_core() if options.num_threads == 1 else contextlib.nullcontext():
        return _run(videos, out_dir, options)


def _run(videos: Sequence[str | Path], out_dir: str | Path, options: RegisterOptions) -> Path:
    paths = [Path(v) for v in videos]
    options.check()
    _check_videos(paths)
    if options.board is not None:
        read_charuco_board(options.board)  # a bad board file fails before any work
    if options.intrinsics is not None:
        read_intrinsics_file(options.intrinsics)  # the same, before every video is probed (seconds each)
    out = Path(out_dir)
    notes = StepNotes()
    unreadable: dict[str, str] = {}
    with collected(notes), timed(notes, "probe"):
        stand_ins = _stand_ins(paths, out, options)
        infos = _probe_all(paths, unreadable, stand_ins)
        _size_stand_ins(infos, options)
    with collected(notes), timed(notes, "motion_test"):
        tracks = capture_tracks(options, out, [info.name for info in infos])
    if tracks is None and options.board is not None:
        require_writable(out)
        with collected(notes), timed(notes, "board_corners"):
            tracks = board_tracks([info.path for info in infos], options.board, out)
        options = dataclasses.replace(options, tracks=tracks.path)  # the report names the file
    check_inputs(options, infos, tracks)
    require_writable(out)
    clear_outputs(out)  # only once the inputs are known good: a typo never costs the last run's results
    names = [info.name for info in infos]
    for info in tqdm(infos, desc="testing camera motion", unit="video", leave=False):
        prepare_video(info, out, options, tracks)
    extract_videos(out, names, options, capture_facts(out, names, options), runner=run_isolated)
    map_capture(out, names, options)
    for name in names:
        localize_video(out, name, options)
    return finish_capture(out, names, options, tracks, notes=notes, unreadable=unreadable)


def check_inputs(options: RegisterOptions, infos: list[ProbedVideo], tracks: Tracks | None) -> None:
    """The inputs registration reads late (`--intrinsics`, `--scale`, `--offsets`), checked before any work or any
    removal."""
    spans = {info.name: info.span for info in infos if info.num_frames}
    declared_offsets(options.synchronized, options.offsets, [info.name for info in infos], spans)
    if options.masks is not None:
        check_mask_folder(options.masks, [info.name for info in infos])
    if options.intrinsics is not None:
        known_intrinsics(options.intrinsics, infos)
    if options.scale is not None:
        a, b, metres = options.scale
        fix = "give two different tracked points and their distance in metres, e.g. --scale l_knee,l_ankle,0.42"
        if a == b or not MIN_SCALE_M <= metres <= MAX_SCALE_M:
            raise InputError(
                None,
                f"--scale {a},{b},{metres:g}: needs two different points {MIN_SCALE_M:g} to {MAX_SCALE_M:g} m apart",
                fix=fix,
            )
        if tracks is not None:
            check_scale_points(options.scale, set(tracks.point), tracks.path)
    if tracks is not None:
        _check_stand_in_sizes(infos, tracks, options)
    named = set(tracks.video_names()) if tracks is not None else set()
    source = (tracks.path if tracks is not None else None) or "the tracks"
    for info in infos:
        if info.rotation and info.name in named:  # a tool that ignores the flag would give the stored frame's pixels
            log.warning(video_io.rotated_pixels_message(info.name, info.rotation, source))


def _check_stand_in_sizes(infos: list[ProbedVideo], tracks: Tracks, options: RegisterOptions) -> None:
    """A name's tracks lie within the image size it was given (--size is one size for every name): pixels beyond it
    would be taken for a lens's edge."""
    for info in (info for info in infos if info.stand_in):
        xy = tracks.of_videos([info.name]).xy
        if not len(xy):
            continue
        x, y = xy.max(axis=0)
        if x > 1.02 * info.width or y > 1.02 * info.height:
            given = "--size" if options.size is not None else str(options.intrinsics)
            raise InputError(
                tracks.path,
                f"video {info.name!r}'s tracks reach x, y = {x:.0f}, {y:.0f} px, beyond its image size "
                f"{info.width}x{info.height} ({given})",
                fix="give each camera's size: --intrinsics with the cameras' calibrated sizes (one --size fits all)",
            )


def check_scale_points(scale: tuple[str, str, float], points: set[str], path: Path | None) -> None:
    """`--scale`'s two points are among `points` (of the tracks or labels file `path`)."""
    missing = [p for p in scale[:2] if p not in points]
    if missing:
        raise InputError(
            path,
            f"--scale point(s) {', '.join(missing)} not in the tracks (points: {_listed(sorted(points))})",
            fix="give two different tracked points and their distance in metres, e.g. --scale l_knee,l_ankle,0.42",
        )


def _listed(names: list[str], most: int = 30) -> str:
    """`names` joined, the first `most` of a longer list and how many there are (never cut short unsaid)."""
    shown = ", ".join(names[:most])
    return shown if len(names) <= most else f"{shown}, ... ({len(names)} in all)"


def _stand_ins(paths: list[Path], out: Path, options: RegisterOptions) -> list[ProbedVideo | None]:
    """With --fps, each VIDEO that is a bare name and no file stands for a video that is not here: its frames are its
    tracks' (the given tracks or WS/tracks.csv); None for the files. Sizes come later (`_size_stand_ins`)."""
    if options.fps is None:
        if options.size is not None:
            log.warning("--size only serves videos that are not here, given with --fps: ignored")
        return stand_in_videos(paths, None, None)  # a bare name that is no file: "no such video", --fps named
    stand_ins = stand_in_videos(paths, options.tracks or out / "tracks.csv", options.fps)
    missing = [video.name for video in stand_ins if video is not None]
    if missing:
        log.info(
            "%d of %d videos are not here (%s): static cameras posed from the subject's tracks",
            len(missing),
            len(paths),
            _listed(missing),
        )
        log.info(
            "%s: frame times from --fps, not measured: cameras.json gives their rate, not times, and the solve tests "
            "each rate against the tracks (a phone's true rate may differ a little: its rate is then fitted)",
            _listed(missing),
        )
    else:
        log.warning("--fps only serves videos that are not here: every video given is a file, so it is ignored")
    return stand_ins


def _size_stand_ins(infos: list[ProbedVideo], options: RegisterOptions) -> None:
    """Each stand-in's image size: --size, else its camera's in --intrinsics, matched over every video (by name,
    else by order, as the intrinsics are)."""
    if not any(info.stand_in for info in infos):
        return
    sizes = intrinsics_sizes(options.intrinsics, infos) if options.intrinsics is not None else {}
    for info in infos:
        if info.stand_in:
            with_size(info, sizes.get(info.name, (0, 0)), options.size, options.intrinsics)


def _probe_all(
    paths: list[Path], unreadable: dict[str, str], stand_ins: list[ProbedVideo | None] | None = None
) -> list[ProbedVideo]:
    """Probe every video (`stand_ins`: those not here, already known). One that cannot be read is left out with its
    one-line reason (a warning and the report), and the others go on; with fewer than two readable videos, the
    first reason is the error."""
    infos, errors = [], []
    known = stand_ins or [None] * len(paths)
    for path, stand_in in tqdm(
        zip(paths, known, strict=True), total=len(paths), desc="probing videos", unit="video", leave=False
    ):
        if stand_in is not None:
            infos.append(stand_in)
            continue
        try:
            infos.append(probe_video(path))
        except InputError as error:
            errors.append(error)
            unreadable[str(path)] = str(error)
            log.warning("left out: %s", error)
    if len(infos) < 2 and errors:
        raise errors[0]
    return infos


def _check_videos(videos: list[Path]) -> None:
    if len(videos) < 2:
        raise InputError(
            videos[0] if videos else None,
            "register needs at least two videos",
            fix="give every video of the scene",
        )
    names = [video_name(v) for v in videos]  # a name that cannot be a folder is the user's to fix, not left out
    twice = first_repeated(names)
    if twice is not None:
        raise InputError(
            videos[twice],
            f"video name {names[twice]!r} is used twice",
            fix="video names (file names without extension) must be unique",
        )
    copy = _first_copy(videos)
    if copy is not None:
        raise InputError(
            videos[copy[1]],
            f"has the same contents as {videos[copy[0]]}: one camera's video given twice",
            fix="give each camera's video once (two cameras at one place have no baseline between them)",
        )


def _first_copy(videos: list[Path]) -> tuple[int, int] | None:
    """(i, j), i < j, of the first two paths with identical contents; files of different sizes are never read."""
    sizes: dict[int, list[int]] = {}
    for j, video in enumerate(videos):
        try:
            size = video.stat().st_size
        except OSError:
            continue  # a missing file is reported where it is opened
        for i in sizes.get(size, []):
            if filecmp.cmp(videos[i], video, shallow=False):  # stops at the first differing block
                return i, j
        sizes.setdefault(size, []).append(j)
    return None


def board_tracks(videos: Sequence[Path], board: Path, out: Path) -> Tracks:
    """`--board` without tracks: the board's corners found in the videos that decode (registration leaves the
    others out too) are the subject's tracks, written to WS/tracks.csv as `import-tracks VIDEO... --board` writes
    them (the solve reads them there)."""
    log.info("no tracks: the board's corners found in the videos are the subject's tracks (%s)", out / "tracks.csv")
    readable = []
    for video in videos:
        try:
            video_io.open_video(video).release()
        except InputError as error:
            log.warning("%s: no board corners looked for: %s", video, error)
            continue
        readable.append(video)
    out.mkdir(parents=True, exist_ok=True)
    write_tracks(out / "tracks.csv", charuco_tracks(readable or videos, board))
    # read back: this run sees the CSV's rounded positions, as a later run reading WS/tracks.csv will
    return read_tracks(out / "tracks.csv").canonical()


def capture_tracks(options: RegisterOptions, out: Path, videos: Sequence[str]) -> Tracks | None:
    """The subject's tracks registration uses (masks, the subject path): the given ones, or WS's tracks.csv; their
    video names matched to `videos` (the capture's video names), rows in canonical order (the same poses whatever
    order the file lists them in)."""
    path = options.tracks or (out / "tracks.csv" if (out / "tracks.csv").exists() else None)
    if path is not None and options.tracks is None and options.board is not None:
        log.info("tracks: %s (delete it to find the board's corners in the videos again)", path)
    return matched_to_videos(read_tracks(path), videos).canonical() if path is not None else None


# ----------------------------------------------------------------------------------------------------------
# The capture's matching and mapping


def map_capture(out: Path, videos: list[str], options: RegisterOptions) -> dict[str, Any]:
    """Merge the videos' feature databases, match, map, keep the largest model (each kept from an earlier run with
    the same inputs); the outcome (the kept model's name, its warnings and seconds) goes to sfm/mapping.json and
    is returned."""
    layout = Layout(out)
    notes = StepNotes()
    steps = StepLog(layout.sfm_dir)
    prepared = [read_prepared(layout.plan(v)) for v in videos]
    names_of = {v: p.images for v, p in zip(videos, prepared, strict=True)}
    extracted = [json.loads(layout.extraction(v).read_text(encoding="utf-8")) for v in videos]
    facts = capture_facts(out, videos)
    with collected(notes):
        with timed(notes, "merge"):
            merge_key = _merge(layout, videos, [e["key"] for e in extracted], steps)
        if any(names_of.values()):
            with timed(notes, "match"):
                pairs, matching = _match(names_of, layout, options, steps, merge_key)
            with timed(notes, "map"):
                infos = [p.plan.info for p in prepared]
                intrinsics = known_intrinsics(options.intrinsics, infos) if options.intrinsics else {}
                models = _map(len(videos), names_of, intrinsics, layout, options, steps, notes)
            model = _largest_model(models, notes, _model_points(layout, models))
        else:  # every video is a name (--fps): no image for background SfM, nothing to warn about
            pairs, matching, models, model = [], {"verified_pairs": 0, "inlier_matches": 0}, {}, None
    notes.reused = steps.reused
    mapping = {
        "model": model,
        "models": models,
        "pairs": len(pairs),
        "matching": matching,
        "masked": facts.masked,
        **notes.to_json(),
    }
    layout.mapping.parent.mkdir(parents=True, exist_ok=True)
    layout.mapping.write_text(json.dumps(mapping, indent=1) + "\n", encoding="utf-8")
    return mapping


def _merge(layout: Layout, videos: list[str], keys: list[str], steps: StepLog) -> str:
    """The merged database (kept while every video's features are those it was merged from); returns its key."""
    key = input_key(videos, keys)
    if steps.result(MERGE_STEP, key) is not None and layout.database.exists():
        return key  # not listed as reused: the report's reused steps are those that cost time
    steps.forget(MERGE_STEP, "match", "map")
    merge_features(layout.out, videos, layout.database)
    steps.record(MERGE_STEP, key, {"videos": videos})
    return key


def _match(
    names_of: dict[str, list[str]], layout: Layout, options: RegisterOptions, steps: StepLog, merge_key: str
) -> tuple[list[tuple[str, str]], dict[str, int]]:
    """Sequential pairs within a video, keyframe and retrieved pairs across videos, matched (kept from an earlier
    run with the same features and pairs); returns the pairs and the matching summary."""
    words = word_vectors(_descriptors(layout.database)) if options.cross_partners > 0 and len(names_of) > 1 else {}
    pairs = build_pairs(
        names_of,
        overlap=options.sequential_overlap,
        keyframes=options.keyframes,
        partners=options.cross_partners,
        words=words,
    )
    key = input_key(merge_key, pairs, options.max_ratio)
    done = steps.result("match", key)
    if done is not None:
        return pairs, steps.reuse("match", {str(k): int(v) for k, v in done.items()})
    steps.forget("match", "map")
    with pycolmap.Database.open(str(layout.database)) as db:
        db.clear_matches()  # an interrupted run's partial matches
        db.clear_two_view_geometries()
    matching: dict[str, int] = run_isolated(
        "matching",
        colmap_steps.match,
        {
            "database": str(layout.database),
            "pairs": pairs,
            "max_ratio": options.max_ratio,
            "num_threads": options.num_threads,
        },
        layout.colmap_log,
    )
    steps.record("match", key, matching)
    return pairs, matching


def _descriptors(database: Path) -> dict[str, np.ndarray]:
    """image name -> its SIFT descriptors (N, 128) uint8, from the feature database."""
    with pycolmap.Database.open(str(database)) as db:
        return {image.name: np.asarray(db.read_descriptors(image.image_id).data) for image in db.read_all_images()}


def _map(
    count: int,
    names_of: dict[str, list[str]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray | None]],
    layout: Layout,
    options: RegisterOptions,
    steps: StepLog,
    notes: StepNotes,
) -> dict[str, int]:
    """The mapper's models in sfm/models/<name> (kept from an earlier run with the same matches and settings);
    returns model name -> registered images."""
    step = colmap_steps.map_global if options.mapper is Mapper.GLOBAL else colmap_steps.map_incremental
    fix_intrinsics = bool(intrinsics) and len(intrinsics) == count
    if intrinsics and not fix_intrinsics:  # COLMAP fixes all intrinsics or none
        notes.warnings.append("known intrinsics for only some videos: all intrinsics are refined")
        log.warning("known intrinsics for %d of %d videos: all intrinsics are refined", len(intrinsics), count)
    key = input_key(steps.steps.get("match", {}).get("key"), options.mapper, fix_intrinsics, options.init_min_inliers)
    done = steps.result("map", key)
    if done is not None and all((layout.model_dir / name).is_dir() for name in done):
        return steps.reuse("map", {str(k): int(v) for k, v in done.items()})
    steps.forget("map")
    if layout.model_dir.exists():
        shutil.rmtree(layout.model_dir)
    layout.model_dir.mkdir()
    models: dict[str, int] = run_isolated(
        f"mapping ({options.mapper.value})",
        step,
        {
            "database": str(layout.database),
            "image_dir": str(layout.frames_dir),
            "out_dir": str(layout.model_dir),
            "fix_intrinsics": fix_intrinsics,
            "init_min_inliers": options.init_min_inliers,
            "num_threads": options.num_threads,
            "num_images": sum(len(n) for n in names_of.values()),
        },
        layout.colmap_log,
    )
    steps.record("map", key, models)
    return models


def _model_points(layout: Layout, models: dict[str, int]) -> dict[str, int]:
    """Each model's 3D points."""
    return {name: int(pycolmap.Reconstruction(str(layout.model_dir / name)).num_points3D()) for name in models}


def _largest_model(models: dict[str, int], notes: StepNotes, points: dict[str, int] | None = None) -> str | None:
    """The name of the model with the most images among those with MIN_MODEL_POINTS 3D points or more (None
    without one); the others are named in a warning. A model without points poses its images on nothing and
    localizes no frame: a helper's handheld pan kept one of 13 images and 0 points, exit 0."""
    thin = {k: n for k, n in (points or {}).items() if n < MIN_MODEL_POINTS}
    if thin:
        notes.warnings.append(
            f"background SfM model(s) {', '.join(f'{k} ({models[k]} images, {n} points)' for k, n in thin.items())} "
            f"have under {MIN_MODEL_POINTS} 3D points: not kept"
        )
    models = {k: v for k, v in models.items() if k not in thin}
    if not models:
        notes.warnings.append(
            "background SfM found no model: no pair of images gave an initial model (too few matches, too narrow "
            "a triangulation angle, or matches on one plane; register_report.json `matching` has the matches)"
        )
        return None
    best = max(models, key=lambda k: models[k])
    if len(models) > 1:
        notes.warnings.append(
            f"{len(models)} models; kept model {best} with {models[best]} images "
            f"(others: {', '.join(f'{k}: {v}' for k, v in models.items() if k != best)})"
        )
    return best


# ----------------------------------------------------------------------------------------------------------
# The capture's result


def finish_capture(
    out: Path,
    videos: list[str],
    options: RegisterOptions,
    tracks: Tracks | None,
    *,
    notes: StepNotes | None = None,
    unreadable: dict[str, str] | None = None,
) -> Path:
    """After every video's `localize_video`: the static videos the background left out posed from the subject's
    tracks, then cameras.json, background.ply and register_report.json, with the warnings and seconds of every
    step (`notes`: the capture's own, before the per-video steps). Returns the cameras.json path; raises
    RegistrationError (after writing the report) when fewer than two videos are posed."""
    layout = Layout(out)
    notes = notes or StepNotes()
    prepared = [read_prepared(layout.plan(v)) for v in videos]
    plans = [p.plan for p in prepared]
    extracted = [StepNotes.from_json(json.loads(layout.extraction(v).read_text(encoding="utf-8"))) for v in videos]
    mapping = json.loads(layout.mapping.read_text(encoding="utf-8"))
    localized = [read_poses(layout.poses(v)) for v in videos]
    results: Results = {v: poses for v, (poses, _) in zip(videos, localized, strict=True)}
    _gather(notes, [p.notes for p in prepared], extracted, StepNotes.from_json(mapping), [n for _, n in localized])
    rec = pycolmap.Reconstruction(str(layout.model_dir / mapping["model"])) if mapping["model"] is not None else None
    summary = _Summary(pairs=mapping["pairs"], matching=mapping["matching"], rec=rec)
    _drop_implausible(results, notes.warnings)
    _drop_no_lens(plans, results, notes.warnings)
    drop_spikes(plans, results, notes.warnings)
    with collected(notes), timed(notes, "background_check"):
        intrinsics = known_intrinsics(options.intrinsics, [p.info for p in plans]) if options.intrinsics else {}
        images = rec.num_reg_images() if rec is not None else None
        summary.two_views = refuse_two_view_focals(images, set(intrinsics), results)
        if summary.two_views:
            names = ", ".join(summary.two_views)
            notes.warnings.append(f"{names}: the background's poses are not used: {TWO_VIEWS_WHY}")
    markers = None
    stale = out / MARKER_TRACKS
    if options.tracks is None or Path(options.tracks).resolve() != stale.resolve():  # never the input, once read
        stale.unlink(missing_ok=True)  # an earlier run's: this run's report would not name it
    if tracks is None and _subject_wanted(plans, results, options):
        with collected(notes), timed(notes, "markers"):
            tracks, markers = tracks_from_markers(plans, out, options.num_threads)
    with collected(notes), timed(notes, "people"):
        tracks, people, summary.people = match_people(plans, tracks, notes.warnings, options.max_offset)
    with collected(notes), timed(notes, "background_check"):
        summary.background_check = check_background(plans, results, tracks, notes.warnings, options.max_offset)
    with collected(notes), timed(notes, "subject"):
        subject_report = pose_from_subject(plans, results, tracks, intrinsics, options, notes.warnings)
    if subject_report is not None and markers is not None:
        subject_report["markers"] = markers
        if subject_report.get("why"):  # the tracks were not the user's: say whose they were
            subject_report["why"] += (
                f" (the tracks were the corners of the {markers['dictionary']} markers in view, {markers['file']})"
            )
    registered_videos = [v for v in plans if any(r.pose is not None for r in results[v.info.name].values())]
    failing = len(registered_videos) < 2
    moving_hint = _moving_hint(plans, registered_videos, tracks, options, failing)
    if moving_hint and not failing:  # a failure says it in its error instead
        notes.warnings.append(moving_hint)
    if failing:
        # a video with some frames posed says how many: "registered" alone read as the whole video
        names = ", ".join(_posed_share(v, results[v.info.name]) for v in registered_videos) or "none"
        _fail(
            out,
            options,
            notes,
            unreadable,
            plans,
            results,
            summary,
            subject_report,
            f"only {len(registered_videos)} of {len(plans)} videos registered ({names})",
            moving_hint,
        )
    with timed(notes, "export"):
        # a model whose every pose the subject refuted has its points in another world than the cameras
        kept = rec if background_left(plans, results) else None
        refuted = set((summary.background_check or {}).get("refuted", {}))
        dropped = {name for p, v in zip(prepared, videos, strict=True) if v in refuted for name in p.images}
        # register, run (check_inputs) and batch (at read) refused unknown names before any work
        declared = options.declared(videos)
        path = _export(registered_videos, results, _points(kept, dropped), subject_report, people, out, declared)
    _write_report(out, options, notes, unreadable, plans, results, summary, subject_report, error=None)
    shutil.rmtree(layout.previous_dir, ignore_errors=True)  # replaced by this run's
    return path


def _gather(
    notes: StepNotes,
    prepared: list[StepNotes],
    extracted: list[StepNotes],
    mapping: StepNotes,
    localized: list[StepNotes],
) -> None:
    """The per-video steps' warnings, seconds (summed over videos) and reused steps into the capture's `notes`, in
    the order the steps run."""
    for part in [*prepared, *extracted, mapping, *localized]:
        notes.warnings.extend(part.warnings)
        for step, seconds in part.timings.items():
            notes.timings[step] = notes.timings.get(step, 0.0) + seconds
    reused = [step for part in prepared for step in part.reused]
    kept = sum(1 for part in extracted if part.reused)
    if kept:
        reused.append("extract" if kept == len(extracted) else f"extract ({kept} of {len(extracted)} videos)")
    notes.reused = reused + mapping.reused


@dataclass(kw_only=True)
class _Summary:
    """What the report says of the background SfM: the pair count, the matching summary and the kept model."""

    pairs: int
    matching: dict[str, int]
    rec: pycolmap.Reconstruction | None
    background_check: dict[str, Any] | None = None  # its static poses against the subject's tracks
    people: dict[str, Any] | None = None  # people numbered per video, matched across videos (sfm/register_people.py)
    two_views: list[str] = dataclasses.field(default_factory=list)  # videos a two-image model of unknown focals posed


def _points(rec: pycolmap.Reconstruction | None, dropped: set[str]) -> tuple[np.ndarray, np.ndarray]:
    """The model's points (N, 3) and colours (N, 3) uint8, without those seen by fewer than two images outside
    `dropped` (images of videos whose poses the subject refuted: what they triangulated is not in the cameras'
    world)."""
    if rec is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    names = {image_id: image.name for image_id, image in rec.images.items()}
    points = [
        p
        for p in rec.points3D.values()
        if not dropped or sum(names[e.image_id] not in dropped for e in p.track.elements) >= 2
    ]
    xyz = np.array([p.xyz for p in points]).reshape(-1, 3)
    return xyz, np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)


def _export(
    registered_videos: list[VideoPlan],
    results: Results,
    points: tuple[np.ndarray, np.ndarray],
    subject_report: dict[str, Any] | None,
    people: dict[str, dict[int, int]],
    out: Path,
    declared: dict[str, float] | None = None,
) -> Path:
    """background.ply (`points`: the model's points and colours) and cameras.json (every posed frame, and each
    video's map of its people when they were matched across videos); returns the cameras.json path. Without a
    clock from the subject path, each video's clock_offset is the `declared` one (--synchronized's 0, --offsets;
    the solve tests them)."""
    cameras = CameraSet()
    subject = subject_report or {}
    # the posed videos' offsets (handheld ones that anchored the subject path) are on the same clock
    clock_offsets = {
        v["name"]: v["offset_s"] for v in subject.get("posed_videos", {}).get("videos", []) if v["reason"] is None
    }
    clock_offsets.update({c["name"]: c["offset_s"] for c in subject.get("cameras", [])})
    written_declared = bool(declared) and not clock_offsets
    if written_declared:
        clock_offsets = dict(declared or {})
        log.info("the declared clock offsets are written to cameras.json (the solve tests them)")
    for video in registered_videos:
        name = video.info.name
        posed = _video_cameras(video, results[name], clock_offsets.get(name), people.get(name))
        posed.clock_declared = written_declared and posed.clock_offset is not None
        cameras.videos.append(posed)
    write_ply(out / "background.ply", *points)
    return write_cameras(out / "cameras.json", cameras)


def _video_cameras(
    video: VideoPlan, results: dict[int, FramePose], clock_offset: float | None, people: dict[int, int] | None
) -> VideoCameras:
    """One video's posed frames in the cameras.json contract."""
    frames = []
    for frame, result in sorted(results.items()):
        if result.pose is None or result.intrinsics is None:
            continue
        K, dist = result.intrinsics
        frames.append(
            FrameCamera(
                frame=frame,
                time=None if video.info.stand_in else float(video.info.times[frame]),
                K=K,
                R=result.pose.rotation.matrix(),
                t=np.asarray(result.pose.translation),
                dist=dist,
            )
        )
    return VideoCameras(
        name=video.info.name,
        width=video.info.width,
        height=video.info.height,
        fps=video.info.fps,
        frames=frames,
        clock_offset=clock_offset,
        people=people,
    )


def _write_report(
    out: Path,
    options: RegisterOptions,
    notes: StepNotes,
    unreadable: dict[str, str] | None,
    videos: list[VideoPlan],
    results: Results,
    summary: _Summary,
    subject: dict[str, Any] | None,
    *,
    error: str | None,
) -> None:
    write_report(
        out / "register_report.json",
        videos=videos,
        results=results,
        timings=notes.timings,
        warnings=notes.warnings,
        options=options,
        reused=notes.reused,
        unreadable=unreadable,
        pairs=summary.pairs,
        matching=summary.matching,
        rec=summary.rec,
        background_check=summary.background_check,
        people=summary.people,
        subject=subject,
        error=error,
    )
    _repeat(notes.warnings)


def _repeat(warnings: list[str]) -> None:
    """The report's warnings logged once more at the end: many were only written to the report (the subject path's
    uncertain poses, a board's intrinsics not taken), and the others are lost among the steps' lines; `run`
    collects them from here."""
    unique = list(dict.fromkeys(warnings))
    if unique:
        log.info("register: %d warning(s) (register_report.json `warnings`), once each:", len(unique))
    for message in unique:
        log.warning("%s", message)


def _moving_hint(
    plans: list[VideoPlan],
    registered: list[VideoPlan],
    tracks: Tracks | None,
    options: RegisterOptions,
    failing: bool = False,
) -> str | None:
    """One line for tracked videos that the motion test found moving and nothing posed (`failing`: also those the
    background posed, in a registration that fails): the subject path poses only static cameras, and a subject
    filling a tripod's view (a board held close, a person walking away from it) can look like camera motion."""
    if options.camera_motion is not CameraMotion.AUTO or tracks is None:
        return None
    tracked = set(tracks.video_names())
    posed = {v.info.name for v in registered}
    lost = [v for v in plans if not v.static and (failing or v.info.name not in posed) and v.info.name in tracked]
    if not lost:
        return None
    reasons = "; ".join(f"{v.info.name}: {v.motion.reason}" for v in lost if v.motion is not None)
    unposed = [v.info.name for v in lost if v.info.name not in posed]
    background = [v.info.name for v in lost if v.info.name in posed]
    fates = [f"{', '.join(unposed)} not posed"] if unposed else []  # each video's own fate, not the first one's
    fates += [f"{', '.join(background)} left to the background"] if background else []
    return (
        f"{', '.join(v.info.name for v in lost)} measured as moving ({reasons}); {', '.join(fates)}; the subject "
        "path poses static cameras only: if they stood still, register (or run) again with --camera-motion static"
    )


def _given_motion_hint(videos: list[VideoPlan], options: RegisterOptions) -> str | None:
    """The videos whose --camera-motion the motion test measured otherwise (the user's word was kept, but a failed
    registration names it as a cause); a test without a single shift measured is no evidence."""
    contradicted = [
        (v.info.name, v.motion.reason)
        for v in videos
        if v.motion_given and v.motion is not None and v.motion.shifts and v.motion.static != v.static
    ]
    if not contradicted:
        return None
    measured = "; ".join(f"{name}: {reason}" for name, reason in contradicted)
    return (
        f"--camera-motion {options.camera_motion.value} was given, but the motion test measured otherwise "
        f"({measured}): register again with --camera-motion auto"
    )


def _drop_implausible(results: Results, warnings: list[str]) -> None:
    """Unpose the frames whose background pose came with intrinsics or a position no camera has (a degenerate
    model: a board-only scene gave k1 = 1452), one warning per video: cameras.json would refuse them unreported."""
    for video, frames in results.items():
        dropped, why = 0, ""
        for frame, result in frames.items():
            if result.pose is None or result.intrinsics is None:
                continue
            K, dist = result.intrinsics
            try:
                check_plausible(K, np.asarray(result.pose.translation), dist, None, f"frame {frame}")
            except InputError as error:
                why = why or error.what
                dropped += 1
                frames[frame] = FramePose(pose=None, reason=f"the background's pose is no camera's: {error.what}")
        if dropped:
            warnings.append(f"{video}: {dropped} frame(s) of the background model left unposed: {why}")


def _posed_share(video: VideoPlan, frames: dict[int, FramePose]) -> str:
    """`name`, or `name: 4 of 27 frames` where some of the frames it was to pose have none."""
    posed = sum(r.pose is not None for r in frames.values())
    return video.info.name if posed == len(frames) else f"{video.info.name}: {posed} of {len(frames)} frames"


def _drop_no_lens(plans: list[VideoPlan], results: Results, warnings: list[str]) -> None:
    """Unpose the videos whose background pose came with a focal no lens has for their image size (62 px for a
    910 px wide GoPro: a model fitted to false matches), and warn that the videos the same model still poses come
    from it. Checked with or without the subject's tracks (their check refutes such poses too)."""
    refuted: dict[str, str] = {}
    for plan in plans:
        name = plan.info.name
        first = next((r for r in results[name].values() if r.pose is not None and r.source != "subject"), None)
        if first is None or first.intrinsics is None:
            continue
        why = no_lens(first.intrinsics[0], plan.info.width, plan.info.height)
        if why is None:
            continue
        refuted[name] = why
        unpose_background(results, name, why)
        warnings.append(f"{name}: the background's pose is not used: {why}")
    rest = [p.info.name for p in plans if any(r.pose is not None for r in results[p.info.name].values())]
    if refuted and rest:
        warnings.append(
            f"{', '.join(rest)}: posed by the same background model as {', '.join(refuted)}, whose intrinsics are no "
            "lens: check them (known intrinsics, --intrinsics, make such a false model less likely)"
        )


def _subject_wanted(plans: list[VideoPlan], results: Results, options: RegisterOptions) -> bool:
    """Whether the subject path would run given tracks: a static video the background left out (or every static
    one, `--subject always`), and markers may be looked for (`find_markers`)."""
    if not options.find_markers or options.subject is SubjectPath.NEVER:
        return False
    if options.scale is not None and not all(p.startswith("marker_") for p in options.scale[:2]):
        return False  # --scale names the points of other tracks: the user means to track the subject
    static = [p for p in plans if p.static]
    if options.subject is SubjectPath.ALWAYS:
        return bool(static)
    return any(all(r.pose is None for r in results[p.info.name].values()) for p in static)


def _background_hints(options: RegisterOptions, videos: list[VideoPlan]) -> list[str]:
    """What could help the background path here: more frames only where a video moves (a static one sends one
    image), known intrinsics only where none were given, the subject's tracks where every video stands still."""
    hints = ["more overlap between the videos' views"]
    if any(not video.static for video in videos):
        hints.append("more frames (--max-frames, --step)")
    if options.intrinsics is None:
        hints.append("known intrinsics (--intrinsics)")
    hints.append(
        "--max-features higher" if all(video.static for video in videos) else "--keyframes / --max-features higher"
    )
    if videos and all(video.static for video in videos):
        hints.append(
            "or the subject's tracks (dynrecon track / import-tracks into the workspace): they pose static cameras"
        )
    elif len(hints) > 1:
        hints[-1] = "or " + hints[-1]
    return hints


def _fail(
    out: Path,
    options: RegisterOptions,
    notes: StepNotes,
    unreadable: dict[str, str] | None,
    videos: list[VideoPlan],
    results: Results,
    summary: _Summary,
    subject: dict[str, Any] | None,
    what: str,
    moving_hint: str | None = None,
) -> NoReturn:
    named = all(v.info.stand_in for v in videos)  # every video a name (--fps): the subject path was the only one
    if named:
        background = "the videos are not here (--fps)"
    elif summary.two_views:
        background = (
            f"the background's model of two images ({', '.join(summary.two_views)}) fixes no focal length (give "
            "--intrinsics)"
        )
    else:
        background = (
            "the static videos' backgrounds gave no model (too few matches between their views: little shared "
            "background, or views too far apart)"
        )
    if subject is not None and subject.get("why"):
        hint = f"{background}, and the subject path could not pose them: {subject['why']}"
    elif named:
        hint = "the videos are not here (--fps): the subject's tracks must be seen by two videos at once"
    else:
        hint = "try " + ", ".join(_background_hints(options, videos))
    if moving_hint:
        hint += f"; {moving_hint}"
    given = _given_motion_hint(videos, options)
    if given:
        hint += f"; {given}"
    previous = Layout(out).previous_dir
    if (previous / "cameras.json").is_file():
        hint += f"; the last successful run's cameras.json is kept in {previous}"
    error = RegistrationError.of(what, hint, out / "register_report.json")
    _write_report(out, options, notes, unreadable, videos, results, summary, subject, error=str(error))
    raise error


__all__ = [
    "ALL_CORES",
    "CameraMotion",
    "Localize",
    "Mapper",
    "RegisterOptions",
    "RegistrationError",
    "SubjectPath",
    "board_tracks",
    "capture_tracks",
    "finish_capture",
    "map_capture",
    "read_cameras",
    "run",
]
