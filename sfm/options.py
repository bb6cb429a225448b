"""The options of the sfm stages (`register`, `import-calibration`): plain dataclasses and enums.

Cheap to import on purpose: the CLI builds its parser from these defaults without loading pycolmap or OpenCV.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

ALL_CORES = -1  # COLMAP's num_threads for one thread per core


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
    tracks: Path | None = None  # tracks.csv for masks (default: WS/tracks.csv when it exists)
    masks: Path | None = None  # user masks folder (see sfm.masks)
    mask_radius: float = 40.0  # original pixels around tracked points
    use_masks: bool = True
    localize: Localize = Localize.AUTO
    inbetween: InBetween = InBetween.TRACK  # how the localized frames are posed (see docs/registration.md)
    min_inliers: int = 30  # PnP inliers needed to accept a localized frame
    init_min_inliers: int = 100  # two-view inliers the mapper needs for its initial pair (COLMAP default)
    num_threads: int = ALL_CORES


class CalibrationFormat(enum.Enum):
    AUTO = "auto"
    QCA = "qca"
    TOML = "toml"  # every TOML layout: Pose2Sim/anipose/FreeMoCap [cam_N], caliscope [cameras.N] and [cam_N]


class Units(enum.Enum):
    """Length unit of TOML translations. AUTO: mm for FreeMoCap files (`[metadata] charuco_square_size`), else m."""

    AUTO = "auto"
    M = "m"
    MM = "mm"


@dataclass(kw_only=True)
class ImportCalibrationOptions:
    """Options of `sfm.import_calibration`; every field is a `dynrecon import-calibration` flag."""

    format: CalibrationFormat = CalibrationFormat.AUTO
    units: Units = Units.AUTO  # TOML translations' unit (see Units)
    scale: float = 1.0  # multiplies the world coordinates (after conversion to metres)


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
]
