"""The options of the sfm stages (`register`, `import-calibration`): plain dataclasses and enums.

Cheap to import on purpose: the CLI builds its parser from these defaults without loading pycolmap or OpenCV.
"""

from __future__ import annotations

import argparse
import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from dynrecon.arguments import named_values
from dynrecon.errors import InputError
from tracking.pixels import DltPixels

MAX_OFFSET_S = 10.0  # seconds searched each way for two videos' clock offset, unless --max-offset says otherwise

ALL_CORES = -1  # COLMAP's num_threads for one thread per core
MAX_COUNT = 10**7  # no count flag of registration is sensibly larger
# pycolmap's CameraModelId names (without INVALID), kept here so that the options stay cheap to import
CAMERA_MODELS = (
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL",
    "RADIAL_FISHEYE",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
    "SIMPLE_DIVISION",
    "DIVISION",
    "SIMPLE_FISHEYE",
    "FISHEYE",
    "EUCM",
    "EQUIRECTANGULAR",
)


class Mapper(enum.Enum):
    INCREMENTAL = "incremental"
    GLOBAL = "global"


class Localize(enum.Enum):
    """Which frames besides the SfM frames get a pose by PnP."""

    AUTO = "auto"  # TRACKED when tracks exist, else ALL
    ALL = "all"
    TRACKED = "tracked"
    NONE = "none"


class InBetween(enum.Enum):
    """How the frames between the SfM keyframes of a moving video are posed (both by PnP against the model)."""

    TRACK = "track"  # the keyframes' features carried by optical flow; SIFT where tracking fails
    SIFT = "sift"  # SIFT features of every frame matched to the model


class KeyframeSelection(enum.Enum):
    """How a moving video's SfM frames (keyframes) are chosen."""

    CONTENT = "content"  # a new keyframe where the view has moved enough (sfm/keyframes.py); capped at max_frames
    EVEN = "even"  # every step-th frame or one per time_step, thinned evenly to max_frames


class CameraMotion(enum.Enum):
    """Whether a video's camera moves: measured per video (AUTO) or set by the user for all videos."""

    AUTO = "auto"
    STATIC = "static"
    MOVING = "moving"


class SubjectPath(enum.Enum):
    """When static videos are posed from the moving subject's tracks."""

    AUTO = "auto"  # for static videos the background did not pose, when tracks exist
    ALWAYS = "always"  # every static video, anchored on the background's poses where there are some
    NEVER = "never"


@dataclass(kw_only=True)
class RegisterOptions:
    """Options of `sfm.register`; every field is a `dynrecon register` flag (see `sfm/register_cli.py`)."""

    keyframes_by: KeyframeSelection = KeyframeSelection.CONTENT
    # A new keyframe when the tracked corners moved by this share of the long side (median) since the last one,
    # or when fewer than keyframe_survival of its corners are still tracked (content selection).
    keyframe_motion: float = 0.05
    keyframe_survival: float = 0.6
    step: int = 0  # even selection (implied when set): every Nth decoded frame (0: all, then thinned)
    time_step: float | None = None  # even selection (implied when set): or one frame per this many seconds
    max_frames: int = 150  # SfM frames per video at most (content: a cap; even: the count)
    long_side: int = 1280  # SfM frames are resized to this long side (pixels)
    max_features: int = 4096  # SIFT features per frame
    # A static video's background image is matched across wide baselines: more features, DSP-SIFT with affine
    # shapes (see docs/registration.md).
    background_features: int = 16384
    camera_motion: CameraMotion = CameraMotion.AUTO
    subject: SubjectPath = SubjectPath.AUTO
    scale: tuple[str, str, float] | None = None  # (point A, point B, metres) for the subject path's scale
    # A triggered rig: the videos share one clock. The subject path fits each pair at offset 0 unless the pair's
    # tracks clearly prefer another offset (then the claim is reported contradicted for that pair)
    synchronized: bool = False
    # Known clock offsets per video name (s, global = own time + offset): claimed and tested as --synchronized's 0s
    offsets: dict[str, float] = field(default_factory=dict)
    # Seconds the subject path searches each way for a pair's clock offset: videos started further apart need more
    max_offset: float = MAX_OFFSET_S
    max_ratio: float = 0.8  # SIFT ratio test
    sequential_overlap: int = 5  # pairs (i, i+1..i+overlap) within a video
    keyframes: int = 10  # per video, evenly spaced; each is matched with every one of the other videos
    # Optionally also every SfM frame with its cross_partners most similar SfM frames (visual words) of each
    # other video; off by default: on the video sample the extra pairs made the model worse (docs/registration.md).
    cross_partners: int = 0
    # Incremental by measurement: global put a camera at a wrong pose from false wide-baseline matches
    # (docs/measurements.md).
    mapper: Mapper = Mapper.INCREMENTAL
    camera_model: str = "SIMPLE_RADIAL"
    intrinsics: Path | None = None  # cameras.json / calib .toml / .qca with known intrinsics per video (fixed)
    # A ChArUco board (caliscope's charuco.toml / config.toml) whose corners are in the tracks: the subject path's
    # intrinsics (videos without --intrinsics) and scale (without --scale) come from it (sfm/board.py).
    board: Path | None = None
    # Without tracks: where the background leaves a static video out, the corners of fiducial markers in view
    # (ArUco, AprilTag) are the subject's tracks, and the motion test masks markers that move
    # (sfm/register_markers.py); markers in one video only are named in the error (sfm/board_hint.py). Off where
    # the user's tracks come later (the pipeline's background registration with labels, --tracks or --board).
    find_markers: bool = True
    tracks: Path | None = None  # tracks.csv for masks (default: WS/tracks.csv when it exists)
    # Videos that are not here (2D tracks shared without them): each VIDEO that is no file is a name, its frames
    # those of the tracks of that name at `fps` (one rate, or one per name), its image size `size` or its camera's
    # in --intrinsics. A camera
    # with no pixels is taken as static and posed from the subject's tracks (sfm/video_standin.py).
    fps: float | dict[str, float] | None = None
    size: tuple[int, int] | None = None
    masks: Path | None = None  # user masks folder (see sfm.masks)
    mask_radius: float = 40.0  # original pixels around tracked points
    use_masks: bool = True
    localize: Localize = Localize.AUTO
    inbetween: InBetween = InBetween.TRACK  # how the localized frames are posed (see docs/registration.md)
    min_inliers: int = 30  # PnP inliers needed to accept a localized frame
    init_min_inliers: int = 100  # two-view inliers the mapper needs for its initial pair (COLMAP default)
    num_threads: int = ALL_CORES

    def declared(self, names: Iterable[str]) -> dict[str, float]:
        """The clock offsets the user declared for those of the videos `names` that have one: 0 for all with
        `synchronized`, else `offsets` (names were checked before any work: `declared_offsets`)."""
        if self.synchronized:
            return dict.fromkeys(names, 0.0)
        return {name: self.offsets[name] for name in names if name in self.offsets}

    @property
    def declared_flag(self) -> str:
        """The flag that declared the offsets, for messages."""
        return "--synchronized" if self.synchronized else "--offsets"

    def check(self) -> None:
        """A one-line InputError naming the first flag whose value no registration can use (before any work)."""
        counts = {
            "--max-frames": (self.max_frames or 2, 2),  # 0: no cap
            "--long-side": (self.long_side, 64),
            "--max-features": (self.max_features, 100),
            "--background-features": (self.background_features, 100),
            "--init-min-inliers": (self.init_min_inliers, 8),
            "--min-inliers": (self.min_inliers, 4),
            "--keyframes": (self.keyframes, 1),
            "--step": (self.step, 0),
            "--overlap": (self.sequential_overlap, 0),
            "--cross-partners": (self.cross_partners, 0),
        }
        for flag, (value, least) in counts.items():
            if not least <= value <= MAX_COUNT:
                raise InputError(
                    None,
                    f"{flag} {value}: must be a whole number from {least} to {MAX_COUNT:,}",
                    fix=f"give {flag} >= {least}",
                )
        ranges = {
            "--keyframe-motion": (self.keyframe_motion, 0.0, 1.0),
            "--keyframe-survival": (self.keyframe_survival, 0.0, 1.0),
            "--max-ratio": (self.max_ratio, 0.0, 1.0),
        }
        if self.use_masks:
            ranges["--mask-radius"] = (self.mask_radius, 0.0, 1e5)
        for flag, (number, low, high) in ranges.items():
            if not (math.isfinite(number) and low < number <= high):
                raise InputError(
                    None,
                    f"{flag} {number}: must be above {low:g} and at most {high:g}",
                    fix=f"give {flag} in that range",
                )
        if self.num_threads != ALL_CORES and not 1 <= self.num_threads <= MAX_COUNT:
            raise InputError(None, f"--threads {self.num_threads}: give 1 or more, or {ALL_CORES} for all cores")
        if self.time_step is not None and not (math.isfinite(self.time_step) and self.time_step > 0):
            raise InputError(
                None, f"--time-step {self.time_step}: must be a positive number of seconds", fix="e.g. --time-step 0.5"
            )
        if self.camera_model not in CAMERA_MODELS:
            raise InputError(
                None,
                f"--camera-model {self.camera_model!r} is not a COLMAP camera model",
                fix=f"one of {', '.join(CAMERA_MODELS)}",
            )
        if self.fps is not None and self.camera_motion is CameraMotion.MOVING:
            raise InputError(
                None,
                "--fps poses videos that are not here from the subject's tracks, which needs static cameras: not with "
                "--camera-motion moving",
                fix="give the moving videos' files",
            )
        if self.fps is not None and self.subject is SubjectPath.NEVER:
            raise InputError(
                None,
                "--fps poses videos that are not here from the subject's tracks: not with --subject never",
                fix="leave --subject out",
            )


class CalibrationFormat(enum.Enum):
    AUTO = "auto"
    QCA = "qca"
    TOML = "toml"  # every TOML layout: Pose2Sim/anipose/FreeMoCap [cam_N], caliscope [cameras.N] and [cam_N]
    CAMERAS_JSON = "json"  # dynrecon's own cameras.json of another recording by the same static cameras
    DANNCE = "dannce"  # DANNCE / Label3D MATLAB files: a *_dannce.mat, or a folder of cam*_params.mat
    DLT = "dlt"  # 11 DLT coefficients per camera: DLTdv / easyWand *_dltCoefs.csv, Argus *-dlt-coefficients.csv


class Units(enum.Enum):
    """Length unit of TOML translations. AUTO: mm where `[metadata]` gives the board's square in mm (FreeMoCap,
    sleap-anipose) or the cameras are over 100 units apart (an anipose rig in the board's mm), else m. DANNCE's
    files: mm unless M."""

    AUTO = "auto"
    M = "m"
    MM = "mm"


@dataclass(kw_only=True)
class ImportCalibrationOptions:
    """Options of `sfm.import_calibration`; every field is a `dynrecon import-calibration` flag."""

    format: CalibrationFormat = CalibrationFormat.AUTO
    units: Units = Units.AUTO  # TOML translations' unit (see Units)
    pixels: DltPixels = DltPixels.AUTO  # a DLT file's pixel convention (the tool that wrote it)
    profile: Path | None = None  # a DLT file's camera profile (easyWand / Argus / DLTdv: the lenses' distortion)
    scale: float = 1.0  # multiplies the world coordinates (after conversion to metres)
    # The videos were recorded on one clock (a triggered rig): every video's clock_offset is 0, which the solve
    # then tests against its own clocks (it keeps whichever fits better)
    synchronized: bool = False
    # Known clock offsets per video name (s, global time = own time + offset: a clap, a timecode), written as
    # cameras.json clock_offset and tested by the solve like registration's; videos left out get none
    offsets: dict[str, float] = field(default_factory=dict)
    # Videos that are not here (a lab's calibration and tracks shared without them): a VIDEO that is no file is a
    # name, with frames 0 to its last tracked frame in `tracks` (default: the workspace's tracks.csv) at `fps`, and
    # its camera's calibrated image size or `size` (width, height); `fps`: one rate, or one per name
    fps: float | dict[str, float] | None = None
    tracks: Path | None = None
    size: tuple[int, int] | None = None


def declared_offsets(
    synchronized: bool,
    offsets: dict[str, float],
    names: list[str],
    spans: dict[str, tuple[float, float]] | None = None,
) -> dict[str, float]:
    """The clock offsets the user declared for the videos `names`: 0 for all with `synchronized` (a triggered rig),
    else `offsets` (a clap, a timecode); a one-line InputError for both at once, an unknown name, a non-number, or
    (given each video's own time span, `spans`: first and last frame's time, s) offsets under which a declared
    video shares no time with any other declared one."""
    if synchronized and offsets:
        raise InputError(
            None, "--synchronized and --offsets both given", fix="give one: --synchronized means every offset is 0"
        )
    if synchronized:
        return dict.fromkeys(names, 0.0)
    for name, offset in offsets.items():
        if name not in names:
            raise InputError(
                None,
                f"--offsets names video {name!r}, which is not among the videos ({', '.join(names)})",
                fix="name each video by its file name without extension, e.g. --offsets cam1=0,cam2=0.033",
            )
        if not math.isfinite(offset):
            raise InputError(None, f"--offsets {name}={offset}: not a finite number of seconds", fix="give seconds")
    if spans is not None:
        _refuse_disjoint(offsets, spans)
    return dict(offsets)


def _refuse_disjoint(offsets: dict[str, float], spans: dict[str, tuple[float, float]]) -> None:
    """Declared videos that share no time with the others (alone, or in groups apart from each other): no point is
    seen twice at one time across them, and a solve on those clocks would fit each apart (offsets typed in
    milliseconds do this). The error names the video of the smaller group whose offset is largest."""
    placed = {name: (spans[name][0] + t, spans[name][1] + t) for name, t in offsets.items() if name in spans}
    group = {name: name for name in placed}

    def root(name: str) -> str:
        while group[name] != name:
            name = group[name]
        return name

    for a, (sa, ea) in placed.items():
        for b, (sb, eb) in placed.items():
            if a < b and sa <= eb and sb <= ea:
                group[root(a)] = root(b)
    members: dict[str, list[str]] = {}
    for name in placed:
        members.setdefault(root(name), []).append(name)
    if len(members) < 2:
        return
    largest = max(members.values(), key=len)
    name = max((n for n in placed if n not in largest), key=lambda n: abs(offsets[n]))
    start, end = placed[name]
    apart = [n for n in placed if root(n) != root(name)]
    raise InputError(
        None,
        f"--offsets {name}={offsets[name]:g} puts its {spans[name][1] - spans[name][0]:.3g} s at {start:.6g}-{end:.6g} "
        "s, sharing no time with " + ", ".join(f"{n} ({placed[n][0]:.6g}-{placed[n][1]:.6g} s)" for n in apart),
        fix="offsets are seconds (33 ms is 0.033), global time = the video's own time + offset",
    )


OFFSETS_HELP = (
    "known clock offsets in seconds per video (global time = the video's own time + offset: from a clap or a "
    "timecode), e.g. cam1=0,cam2=0.033; written to cameras.json, which the solve tests against the tracks like "
    "registration's offsets"
)


def parse_offsets(text: str) -> dict[str, float]:
    """NAME=SECONDS,... -> {name: seconds}; a one-line argparse error otherwise."""
    from sfm.cameras import MAX_SECONDS  # numpy: not for the command list

    out: dict[str, float] = {}
    for name, value, item in named_values(text, "NAME=SECONDS", "cam2=0.033"):
        try:
            seconds = float(value)
        except ValueError:
            seconds = math.nan
        if not math.isfinite(seconds):
            raise argparse.ArgumentTypeError(f"{item!r}: give NAME=SECONDS once per video, e.g. cam2=0.033")
        if abs(seconds) >= MAX_SECONDS:
            raise argparse.ArgumentTypeError(f"{item!r}: clock offsets are seconds below {MAX_SECONDS:g} in magnitude")
        out[name] = seconds
    return out


__all__ = [
    "ALL_CORES",
    "CalibrationFormat",
    "CameraMotion",
    "ImportCalibrationOptions",
    "InBetween",
    "KeyframeSelection",
    "Localize",
    "Mapper",
    "RegisterOptions",
    "SubjectPath",
    "Units",
    "declared_offsets",
    "parse_offsets",
]
