"""Inputs and outputs of `calibrate_from_subject` (the public dataclasses and error)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from dynrecon.errors import DynreconError
from sfm.options import MAX_OFFSET_S


class SubjectCalibrationError(DynreconError):
    """The tracks cannot pose the cameras; the message says what to change."""


class ScalePointsError(SubjectCalibrationError):
    """The scale's two points are never triangulated at one time: the cameras are posed, the scale is not."""


@dataclass(kw_only=True)
class SubjectVideo:
    """One static camera and the decode times of its frames."""

    name: str
    width: int
    height: int
    times: np.ndarray  # (F,) seconds of each decoded frame in the video's own clock
    K: np.ndarray | None = None  # (3, 3) known intrinsics (OpenCV pixels), None = estimate
    dist: np.ndarray | None = None  # OpenCV k1, k2, p1, p2[, k3], None = none (or estimated k1 when K is None)
    cam_from_world: tuple[np.ndarray, np.ndarray] | None = None  # (R (3, 3), t (3,)) known pose: kept fixed


SEED = 0  # of the pair search's RANSAC sampling
MIN_SHARED = 15  # interpolated correspondences needed for a pair
INLIER_PX = 3.0  # RANSAC threshold (pixels) of marker-grade tracks: clicks, tracked labels, board corners
# Noise scales the subject path tries (pixels): marker-grade tracks, then a pose detector's keypoints
NOISE_SCALES_PX = (INLIER_PX, 2 * INLIER_PX)
MIN_DISTINCT = 25  # distinct positions (2 % cells in both images) a pair needs to be trusted
MIN_RATIO = 1.05  # runner-up ratio below which a pair's time offset is ambiguous
CLAIM_RATIO = 1.2  # a declared offset is contradicted when the searched one scores this much better, a frame away
UNTESTED = "untested"  # a pair's `claim` where its tracks give no geometry to test the declared offsets with
# How a camera's refusal begins where no pair with it held (`calibrate._why`): the reasons a wider offset search
# (--max-offset) could mend, which `register` hints at
NO_USABLE_PAIR = "no usable pair"
NEVER_OVERLAP = "its tracks never overlap in time with another video's"
UNPAIRED = (NO_USABLE_PAIR, NEVER_OVERLAP)
MAX_RESIDUAL_PX = 6.0  # a camera whose median reprojection error ends above this is refused (at INLIER_PX)
MIN_INLIERS = 30  # a camera whose pose rests on fewer agreeing observations is refused


def max_residual_px(inlier_px: float) -> float:
    """The median reprojection error above which a camera is refused, at the noise scale `inlier_px`."""
    return MAX_RESIDUAL_PX * inlier_px / INLIER_PX


class Lens(Enum):
    """Lens model of the cameras without known intrinsics."""

    AUTO = "auto"  # radial distortion when it predicts held-out observations better, else focal only
    FOCAL = "focal"  # focal from self-calibration, no distortion at the start (k1, k2 start at 0)
    RADIAL = "radial"  # radial distortion estimated from the pairs' epipolar geometry before the focal


@dataclass(kw_only=True)
class SubjectOptions:
    max_offset: float = MAX_OFFSET_S  # seconds searched each way for a pair's time offset
    scale: tuple[str, str, float] | None = None  # (point A, point B, metres): mean |A-B| sets the scale
    # Known clock offsets (s, global = own + offset; e.g. from an earlier solve): pairs are fitted at the offsets
    # they imply instead of searched.
    offsets: dict[str, float] | None = None
    # Declared clock offsets (a triggered rig: all 0): tested per pair against the searched offset, used where
    # the tracks do not clearly prefer another (known `offsets` are used untested)
    claimed_offsets: dict[str, float] | None = None
    lens: Lens = Lens.AUTO  # cameras without known intrinsics (the stability folds reuse the chosen one)
    # The tracks' noise scale in pixels (RANSAC threshold; outliers and refusals scale with it). None: INLIER_PX
    # in `calibrate_from_subject`; `choose_noise` measures which of NOISE_SCALES_PX the tracks support.
    inlier_px: float | None = None
    # Relative focal prior of a bundle already adjusted at the self-calibrated focals, adjusted again with it (the
    # stability folds reuse the solution's); None: AUTO loosens it where held-out observations say so
    focal_sigma: float | None = None
    # Per video: the focal (px) to start from and pull the bundle's towards instead of the self-calibrated one (the
    # stability folds of a loosened solution get its focals: they test the poses at the solution's intrinsics)
    focals: dict[str, float] | None = None


@dataclass(kw_only=True)
class SubjectCamera:
    name: str
    K: np.ndarray  # (3, 3)
    dist: np.ndarray | None  # OpenCV's (4,), (5,) or (8,), or None
    R: np.ndarray  # (3, 3) cam_from_world, OpenCV
    t: np.ndarray  # (3,)
    offset: float  # seconds: global_time = own_time + offset
    inliers: int  # observations kept by the bundle adjustment
    residual_px: float  # median reprojection error after bundle adjustment

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass(kw_only=True)
class PairResult:
    a: str
    b: str
    offset: float  # seconds, o_b - o_a (global = own + o)
    inliers: int
    shared: int
    runner_up_ratio: float  # best score / best score further than one frame period from the best (>= 1)
    degenerate: str | None  # "line", "plane", "few distinct positions (...)" or None
    ambiguous: bool = False  # runner_up_ratio below MIN_RATIO: the offset is trusted only without better pairs
    distinct: int = 0  # distinct positions among the pair's inliers
    reason: str | None = None  # why the pair is unusable, None when usable
    claim: str | None = None  # with declared offsets: "held", or why the tracks contradict them


@dataclass(kw_only=True)
class NoiseTrial:
    """The subject path at one noise scale, as `choose_noise` compared it."""

    posed: int = 0
    stable: int = 0  # posed cameras the folds reproduce
    # median over the stable cameras of each one's largest rotation change between a fold and the whole (inf: none)
    fold_rotation_deg: float = float("inf")
    failed: str | None = None  # why the path failed at this scale

    def to_json(self) -> dict[str, object]:
        if self.failed is not None:
            return {"failed": self.failed}
        spread = self.fold_rotation_deg
        return {
            "posed": self.posed,
            "stable": self.stable,
            "fold_rotation_deg": round(spread, 3) if spread != float("inf") else None,
        }


@dataclass(kw_only=True)
class SubjectResult:
    cameras: list[SubjectCamera]  # only the posed ones
    pairs: list[PairResult]
    failed: dict[str, str]  # video name -> why it could not be posed
    metric: bool  # True when the scale came from options.scale or from anchors
    points: dict[str, np.ndarray] = field(default_factory=dict)  # point name -> (T, 3) trajectory samples
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) global times of the `points` samples
    lens: Lens = Lens.FOCAL  # the lens model used (FOCAL or RADIAL)
    # held-out median reprojection error (pixels) of each lens model tried, when AUTO compared them
    lens_check: dict[str, float] = field(default_factory=dict)
    inlier_px: float = INLIER_PX  # the noise scale used
    focal_sigma: float | None = None  # the loosened focal prior kept, None = the self-calibrated focals' prior
    noise_check: dict[float, NoiseTrial] = field(default_factory=dict)  # per scale `choose_noise` tried
    set_aside: list[str] = field(default_factory=list)  # videos left out so that the others are determined

    def camera(self, name: str) -> SubjectCamera | None:
        return next((c for c in self.cameras if c.name == name), None)


def reasons_text(failed: dict[str, str]) -> str:
    """`failed` (video -> why) as one text, the videos with the same reason named together (a group of cameras
    refused for one cause reads once)."""
    by_reason: dict[str, list[str]] = {}
    for name, why in failed.items():
        by_reason.setdefault(why, []).append(name)
    return "; ".join(f"{', '.join(names)}: {why}" for why, names in by_reason.items())
