"""`dynrecon import-tracks`: other tools' 2D points into `tracks.csv`, with renaming and a confidence
threshold.

Formats: DeepLabCut CSV and .h5, SLEAP .slp and analysis HDF5, OpenPose JSON per frame, DLTdv's and Argus's
`*xypts.csv` (tracking/import_dltdv.py), plain `video,frame,point,x,y[,score]` CSV, and videos of a ChArUco board
(`--board charuco.toml`: its corners, see tracking/charuco.py). Imported rows get `source` = the format name and
`score` = the tool's confidence. When the output exists, its rows for other videos and its manual labels
(`source=label`) are kept; the labels win over imported rows on the same frame and point.
"""

from __future__ import annotations

import enum
import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dynrecon.atomic import keep_aside
from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES, first_repeated
from dynrecon.readers import check_video_name
from tracking.detections import Detection
from tracking.import_dlc import H5_SUFFIXES, read_dlc, video_name_from_dlc
from tracking.import_dltdv import is_dltdv_points, read_dltdv_points
from tracking.import_openpose import BODY_25, BODY_25B, read_openpose, video_name_from_openpose
from tracking.import_sleap import is_sleap_analysis, read_sleap_analysis, read_sleap_slp, video_name_from_sleap
from tracking.pixels import DltPixels
from tracking.tracks import SOURCE_LABEL, Tracks, read_tracks, write_tracks

log = logging.getLogger(__name__)

SCORE_COLUMNS = ("score", "likelihood", "confidence")


class Format(enum.Enum):
    AUTO = "auto"
    DLC = "dlc"
    SLEAP = "sleap"  # SLEAP's .slp or analysis HDF5
    OPENPOSE = "openpose"
    CSV = "csv"
    DLTDV = "dltdv"  # DLTdv's or Argus's *xypts.csv: every camera in one file
    CHARUCO = "charuco"  # the inputs are videos; corners of the board given by ImportOptions.board


@dataclass(kw_only=True)
class ImportOptions:
    format: Format = Format.AUTO
    video: str | None = None  # video name for DLC/OpenPose input; default from the file name
    mapping: dict[str, str] = field(default_factory=dict)  # old point name -> new
    drop_unmapped: bool = False  # with a mapping, keep only the points it names
    min_score: float = 0.0  # detections with a lower confidence are left out
    # OpenPose people (linked through the frames), DeepLabCut individuals or SLEAP tracks, numbered by how much they
    # are seen: which one to import (OpenPose: None = 0, the one seen most; the others: None = each under its name)
    person: int | None = None
    every_person: bool = False  # every person / individual, points named person<N>_<keypoint>
    board: Path | None = None  # ChArUco: caliscope's charuco.toml (or config.toml with a [charuco] table)
    # DLTdv / Argus: the videos of cam1, cam2... in order (their names, and their heights for bottom-up rows)
    videos: list[Path] = field(default_factory=list)
    pixels: DltPixels = DltPixels.AUTO  # DLTdv / Argus: the tool's pixel convention


def parse_mapping(text: str) -> dict[str, str]:
    """`--map old=new,old2=new2` -> {old: new}."""
    mapping: dict[str, str] = {}
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        old, sep, new = item.partition("=")
        if not sep or not old.strip() or not new.strip():
            raise InputError(None, f"--map: {item!r} is not old=new", fix="write --map nose=head,lwrist=wrist_l")
        if old.strip() in mapping:
            raise InputError(None, f"--map: {old.strip()!r} is mapped twice")
        mapping[old.strip()] = new.strip()
    return mapping


def detect_format(path: Path) -> Format:
    if path.suffix.lower() in VIDEO_SUFFIXES:
        return Format.CHARUCO
    if path.is_dir() or path.suffix.lower() == ".json":
        return Format.OPENPOSE
    if path.suffix.lower() == ".slp":
        return Format.SLEAP
    if path.suffix.lower() in H5_SUFFIXES:
        return Format.SLEAP if is_sleap_analysis(path) else Format.DLC
    try:
        with path.open(encoding="utf-8-sig") as handle:  # a spreadsheet's byte-order mark is not a column name
            first = handle.readline()
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except UnicodeDecodeError:
        raise InputError(path, "not UTF-8 text", fix="give a CSV or OpenPose JSON file") from None
    except OSError as error:  # no permission, a special file
        raise InputError(path, f"cannot read: {error.strerror or error}") from None
    head = re.split(r"[,;\t|]", first)[0].strip().lower()  # another separator is said by the DLC reader
    if head in ("scorer", "individuals", "bodyparts"):
        return Format.DLC
    if is_dltdv_points(first):
        return Format.DLTDV
    return Format.CSV


def read_detections(path: Path, options: ImportOptions) -> tuple[Format, list[Detection]]:
    fmt = detect_format(path) if options.format is Format.AUTO else options.format
    if fmt not in (Format.OPENPOSE, Format.DLC, Format.SLEAP) and (options.every_person or options.person is not None):
        raise InputError(
            path,
            f"--person applies to OpenPose JSON, DeepLabCut and SLEAP files, not to {fmt.value} input",
            fix="leave --person out",
        )
    if fmt is Format.DLC:
        return fmt, read_dlc(path, options.video or video_name_from_dlc(path), options.person, options.every_person)
    if fmt is Format.SLEAP and path.suffix.lower() == ".slp":
        return fmt, read_sleap_slp(path, options.video, options.person, options.every_person)
    if fmt is Format.SLEAP:
        return fmt, read_sleap_analysis(
            path, options.video or video_name_from_sleap(path), options.person, options.every_person
        )
    if fmt is Format.OPENPOSE:
        return fmt, read_openpose(
            path,
            options.video or video_name_from_openpose(path),
            0 if options.person is None else options.person,
            options.every_person,
        )
    if options.videos and fmt is not Format.DLTDV:
        raise InputError(
            path, f"--videos applies to DLTdv / Argus points, not to {fmt.value} input", fix="use --video NAME"
        )
    if fmt is Format.DLTDV:
        return fmt, read_dltdv_points(path, options.videos, options.pixels)
    if fmt is Format.CHARUCO:
        return fmt, _read_charuco(path, options)
    return fmt, _read_plain(path, options.video)


def _read_charuco(path: Path, options: ImportOptions) -> list[Detection]:
    from tracking.charuco import charuco_tracks

    if options.board is None:
        raise InputError(path, "ChArUco corners need the board", fix="add --board charuco.toml (caliscope's)")
    tracks = charuco_tracks([path], options.board, require_any=False)  # run_import judges all the videos
    video = options.video or path.stem
    return [
        Detection(
            video=video,
            frame=int(tracks.frame[i]),
            point=tracks.point[i],
            x=float(tracks.xy[i, 0]),
            y=float(tracks.xy[i, 1]),
            score=None,
            where=f"{path.name} frame {int(tracks.frame[i])}",
        )
        for i in range(len(tracks))
    ]


def _read_plain(path: Path, video: str | None) -> list[Detection]:
    tracks = read_tracks(path)
    score_column = next((c for c in SCORE_COLUMNS if c in tracks.extra), None)
    detections = []
    for i in range(len(tracks)):
        score: float | None = None
        if score_column is not None and tracks.extra[score_column][i].strip():
            text = tracks.extra[score_column][i]
            try:
                score = float(text)
            except ValueError:
                raise InputError(path, f"{score_column} {text!r} is not a number", where=tracks.where(i)) from None
        detections.append(
            Detection(
                video=video or tracks.video[i],
                frame=int(tracks.frame[i]),
                point=tracks.point[i],
                x=float(tracks.xy[i, 0]),
                y=float(tracks.xy[i, 1]),
                score=score,
                where=f"{path.name}:{tracks.where(i)}",
            )
        )
    return detections


MAX_PIXEL = 1e7  # |x|, |y| beyond this is a corrupt value, not a position in any video


def _check_detection(d: Detection, path: Path) -> None:
    """Refuse what no detector writes: a position that is not finite or absurdly far out, a confidence that is
    infinite or negative, a video name that is no plain file name."""
    where = d.where.removeprefix(f"{path.name}:")
    if not (math.isfinite(d.x) and math.isfinite(d.y)) or max(abs(d.x), abs(d.y)) > MAX_PIXEL:
        raise InputError(
            path,
            f"point {d.point!r} at x, y = {d.x:.6g}, {d.y:.6g} is not a position in an image",
            where=where,
            fix="leave a point that was not found empty (NaN), not infinite or huge",
        )
    if d.score is not None and (math.isinf(d.score) or d.score < 0):  # NaN: no confidence (dropped by --min-score)
        raise InputError(
            path, f"point {d.point!r} has confidence {d.score:.6g}", where=where, fix="confidences are 0 or more"
        )
    check_video_name(d.video, path)


LOW_SCORE = 0.5  # a detector's confidence below which its point is more often a guess (occluded) than found
LOW_SHARE = 0.2  # share of an input's detections under LOW_SCORE from which the import says so


def _say_low_scores(path: Path, fmt: Format, detections: list[Detection], min_score: float) -> None:
    """A warning where many of the detections kept are the detector's guesses: DeepLabCut writes every body part on
    every frame, occluded or not, and they derail the solve's clock search and leave it the slow way. Not for the
    other formats: SLEAP writes visible points only, with confidence-map peaks that run lower (docs/formats.md),
    and OpenPose leaves undetected joints at 0."""
    if fmt is not Format.DLC:
        return
    scores = np.array([d.score for d in detections if d.score is not None and d.score >= min_score], dtype=float)
    scores = scores[np.isfinite(scores)]
    if not scores.size or min_score >= LOW_SCORE:
        return
    share = float(np.mean(scores < LOW_SCORE))
    if share >= LOW_SHARE:
        log.warning(
            "%s: %.0f %% of the detections kept have a confidence under %g, mostly the detector's guesses at hidden "
            "points; they can derail the solve's clock search and slow it down: --min-score 0.6 (DeepLabCut's "
            "pcutoff) or higher leaves them out",
            path,
            100 * share,
            LOW_SCORE,
        )


def _refuse_two_openpose_models(rows: dict[tuple[str, int, str], tuple[float, float, str, str]], out: Path) -> None:
    """OpenPose videos named by BODY_25 (its MidHip) beside videos named by BODY_25B (its Head): one point name
    would be different joints in different videos (a camera whose poses did not tell the models apart)."""
    only = {"BODY_25": set(BODY_25) - set(BODY_25B), "BODY_25B": set(BODY_25B) - set(BODY_25)}  # MidHip, Head
    named: dict[str, set[str]] = {model: set() for model in only}
    for (video, _, point), (_, _, source, _) in rows.items():
        for model, names in only.items():
            if source == Format.OPENPOSE.value and point in names:
                named[model].add(video)
    if named["BODY_25"] and named["BODY_25B"]:
        raise InputError(
            out,
            f"OpenPose keypoints named by two models: BODY_25 in {', '.join(sorted(named['BODY_25']))}, BODY_25B in "
            f"{', '.join(sorted(named['BODY_25B']))} (one name would be different joints in different videos)",
            fix="import every video of one model together (the importer tells BODY_25B apart from the poses), or "
            "rename with --map",
        )


def _keep_replaced(
    out: Path,
    replaced: dict[tuple[str, int, str], tuple[float, float]],
    rows: dict[tuple[str, int, str], tuple[float, float, str, str]],
    videos: set[str],
) -> None:
    """Keep a copy of `out` where the import replaces rows of its videos by others (a mistyped --video would wipe
    another video's tracks without a word); importing the same detections again changes nothing and keeps none."""
    new = {key: (x, y) for key, (x, y, source, _) in rows.items() if key[0] in videos and source != SOURCE_LABEL}
    if not replaced or (all(new.get(key) == xy for key, xy in replaced.items()) and len(new) == len(replaced)):
        return
    counts: dict[str, int] = {}
    for video, _, _ in replaced:
        counts[video] = counts.get(video, 0) + 1
    said = ", ".join(f"{count} of {video}" for video, count in sorted(counts.items()))
    keep_aside(out, f"had rows of the imported videos, which the import replaces ({said})")


def run_import(inputs: list[Path], out: Path, options: ImportOptions) -> Path:
    """Import every input into `out`; returns `out`."""
    for given in inputs:
        if Path(given).resolve() == Path(out).resolve():  # rewritten in the importer's form, the user's file is lost
            raise InputError(given, "is also the output (--out)", fix="write the imported tracks to another file")
    rows: dict[tuple[str, int, str], tuple[float, float, str, str]] = {}
    imported_videos: set[str] = set()
    if options.board is not None:  # videos: their names must differ (two phones' IMG_0001.MOV), checked first
        folder = next((Path(p) for p in inputs if Path(p).is_dir()), None)
        if folder is not None:
            raise InputError(
                folder,
                "is a folder; --board finds the board's corners in video files",
                fix=f"give the video files themselves (such as {folder / '*.mp4'})",
            )
        names = [Path(p).stem for p in inputs]
        twice = first_repeated(names)
        if twice is not None:
            raise InputError(
                Path(inputs[twice]),
                f"video name {names[twice]!r} is used twice",
                fix="video names (file names without extension) must be unique: rename one of the videos",
            )
    named: set[str] = set()  # every point name the files give, for --map's check
    for path in inputs:
        fmt, detections = read_detections(Path(path), options)
        kept = 0
        for d in detections:
            _check_detection(d, Path(path))
            named.add(d.point)
            point = options.mapping.get(d.point, None if options.drop_unmapped and options.mapping else d.point)
            # a NaN score is no confidence: left out whenever a minimum is asked for
            if point is None or (d.score is not None and options.min_score > 0 and not d.score >= options.min_score):
                continue
            key = (d.video, d.frame, point)
            if key in rows:
                raise InputError(
                    Path(path),
                    f"two detections of point {point!r} on frame {d.frame} of video {d.video!r}",
                    where=d.where.removeprefix(f"{Path(path).name}:"),  # the error names the file already
                    fix="check --map (two names mapped to one) and the frame numbers (two rows or image names that "
                    "give the same frame)",
                )
            score = "" if d.score is None else f"{d.score:.3f}"
            rows[key] = (d.x, d.y, fmt.value, score)
            imported_videos.add(d.video)
            kept += 1
        log.info("%s: %d of %d detections imported", path, kept, len(detections))
        _say_low_scores(Path(path), fmt, detections, options.min_score)
        if not detections:
            log.warning("%s: no detection in the file", path)
        elif not kept:
            log.warning("%s: every detection was dropped (check --min-score and --map)", path)
    unmatched = sorted(set(options.mapping) - named)
    if unmatched and named:  # a typo leaves names that differ later in the solve; a point never detected, nothing
        log.warning(
            "--map renames %s, which no imported detection names (a typo, or a point never detected); the names "
            "detected: %s",
            ", ".join(map(repr, unmatched)),
            ", ".join(sorted(named)),
        )
    if options.board is not None and not rows and inputs:
        from tracking.charuco import board_not_found, read_charuco_board

        raise board_not_found(read_charuco_board(options.board), Path(inputs[0]))
    if not rows and inputs:  # an empty tracks.csv would only fail later, far from its cause
        raise InputError(
            Path(inputs[0]) if len(inputs) == 1 else None,
            "no detection to import" + ("" if len(inputs) == 1 else f" in any of the {len(inputs)} files"),
            fix="check that the detector wrote its output there, and --min-score and --map",
        )
    kept_extra: dict[str, dict[tuple[str, int, str], str]] = {}  # the user's own columns of the rows kept
    replaced: dict[tuple[str, int, str], tuple[float, float]] = {}
    if out.is_file():
        old = read_tracks(out)
        sources = old.extra.get("source", [""] * len(old))
        scores = old.extra.get("score", [""] * len(old))
        others = {name: values for name, values in old.extra.items() if name not in ("source", "score")}
        kept_extra = {name: {} for name in others}
        for i in range(len(old)):
            key = (old.video[i], int(old.frame[i]), old.point[i])
            if sources[i] == SOURCE_LABEL or old.video[i] not in imported_videos:
                rows[key] = (float(old.xy[i, 0]), float(old.xy[i, 1]), sources[i], scores[i])
                for name, values in others.items():
                    kept_extra[name][key] = values[i]
            else:
                replaced[key] = (float(old.xy[i, 0]), float(old.xy[i, 1]))
    _refuse_two_openpose_models(rows, out)
    _keep_replaced(out, replaced, rows, imported_videos)  # only where the import goes on to write
    keys = list(rows)
    tracks = Tracks.from_rows(
        [(k[0], k[1], k[2], rows[k][0], rows[k][1]) for k in keys],
        source=[rows[k][2] for k in keys],
        score=[rows[k][3] for k in keys],
        **{name: [column.get(k, "") for k in keys] for name, column in kept_extra.items()},
    )
    return write_tracks(out, tracks)
