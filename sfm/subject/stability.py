"""Is a subject calibration determined by the data? Solve again without part of the tracks, and compare.

The subject path has no ground truth to check against, and a poorly constrained problem (few distinct positions,
little motion, a near-planar path) still returns poses with small residuals: its cameras are then set by noise.
Each of the FOLDS folds leaves out every FOLDS-th block of time (alternating blocks, so every fold sees the same
kind of motion); where a camera's pose in a fold differs from the whole-data pose by more than the tolerance, the
pose is not determined by the data and is not trusted.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sfm.cameras import CameraSet, FrameCamera, VideoCameras
from sfm.evaluate import compare
from sfm.subject.calibrate import calibrate_from_subject
from sfm.subject.model import SubjectCalibrationError, SubjectCamera, SubjectOptions, SubjectResult, SubjectVideo
from tracking.tracks import Tracks

log = logging.getLogger(__name__)


BLOCK = 0.5  # seconds of a video's own time per block
FOLDS = 3  # fold k leaves out the blocks whose index is k modulo FOLDS
# A garbage detector, not an accuracy bound: a fold holds 2/3 of the data, so valid poses move too.
MAX_CENTRE = 0.1  # largest centre change between a fold and the whole, fraction of the camera spread
MAX_ROTATION_DEG = 5.0
# Two cameras of which one has a self-calibrated focal are not trusted at all: one pair aimed at one subject does
# not determine its focals (the axes nearly meet: the two-view degeneracy), and the folds, which compare only the
# relative rotation, move with the wrong focal instead of exposing it.
TWO_SELF_CALIBRATED = (
    "two cameras with self-calibrated focal lengths: one pair of views aimed at one subject does not determine them, "
    "and a wrong focal turns the pair by degrees to tens of degrees; give --intrinsics, --board, or a third video"
)
MAX_TRIPLES = 220  # camera triples tried for the fold's similarity (all of them up to 12 cameras)


@dataclass(kw_only=True)
class Stability:
    """Per camera: the difference between each fold's solution and the whole (after a similarity)."""

    # every compared fold's change, in fold order: centre as a fraction of the camera spread, rotation in degrees
    centre_folds: dict[str, list[float]] = field(default_factory=dict)
    rotation_folds: dict[str, list[float]] = field(default_factory=dict)
    unstable: dict[str, str] = field(default_factory=dict)  # camera -> one-line reason
    checked: bool = True  # False when no fold could be solved: the poses are unverified
    why_unchecked: str | None = None

    @property
    def centre(self) -> dict[str, float]:
        """Per camera: the largest centre change over the folds."""
        return {name: max(values) for name, values in self.centre_folds.items()}

    @property
    def rotation_deg(self) -> dict[str, float]:
        """Per camera: the largest rotation change over the folds."""
        return {name: max(values) for name, values in self.rotation_folds.items()}

    def to_json(self) -> dict[str, object]:
        return {
            "checked": self.checked,
            "why_unchecked": self.why_unchecked,
            "centre_pct": {k: round(100 * v, 2) for k, v in self.centre.items()},
            "rotation_deg": {k: round(v, 3) for k, v in self.rotation_deg.items()},
            "centre_folds_pct": {k: [round(100 * v, 2) for v in vs] for k, vs in self.centre_folds.items()},
            "rotation_folds_deg": {k: [round(v, 3) for v in vs] for k, vs in self.rotation_folds.items()},
            "unstable": self.unstable,
        }


def _fold(tracks: Tracks, videos: list[SubjectVideo], fold: int) -> Tracks:
    times = {v.name: v.times for v in videos}
    keep = np.zeros(len(tracks), dtype=bool)
    for row, (video, frame) in enumerate(zip(tracks.video, tracks.frame, strict=True)):
        own = times[video][int(frame)] if video in times and int(frame) < len(times[video]) else 0.0
        keep[row] = int(own // BLOCK) % FOLDS != fold
    return tracks.take(np.flatnonzero(keep))


def _as_cameras(cameras: list[SubjectCamera]) -> CameraSet:
    return CameraSet(
        videos=[
            VideoCameras(name=c.name, width=1, height=1, frames=[FrameCamera(frame=0, K=c.K, R=c.R, t=c.t)])
            for c in cameras
        ]
    )


def check_stability(
    tracks: Tracks,
    videos: list[SubjectVideo],
    result: SubjectResult,
    options: SubjectOptions | None = None,
    solve: Callable[[Tracks, SubjectOptions], SubjectResult] | None = None,
    alone: bool = True,
) -> Stability:
    """Solve each fold of `tracks` and compare its cameras with `result` (the solution on all of them).

    `solve` (fold's tracks, options) -> solution: how `result` was found (default `calibrate_from_subject` on
    `videos`). A similarity needs 3 cameras; with 2, their relative rotation is compared. `alone`: the cameras
    are posed from their own tracks (False: beside videos the background posed, which constrain their focals)."""
    posed = {c.name for c in result.cameras}
    if alone and pair_without_intrinsics([v for v in videos if v.name in posed]):
        return Stability(unstable={c.name: f"not determined: {TWO_SELF_CALIBRATED}" for c in result.cameras})
    centres = np.array([c.centre for c in result.cameras]) if result.cameras else np.zeros((0, 3))
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max() * 2) if len(centres) else 0.0
    out = Stability()
    verified: set[str] = set()
    failures = []
    # The folds keep the whole solution's clock offsets: they test the geometry, and skip the offset search.
    # ... and its lens model and noise scale: the folds test the poses, not the model choice. Where the solution
    # loosened its focal prior, the folds start from its focals and keep them as the prior's centre (with the
    # loosened sigma): a fold's own self-calibrated focal, from a third less data, can be far off, and under the
    # loose prior the fold then settles on another focal and scale (docs/registration.md, step 4).
    fold_options = dataclasses.replace(
        options or SubjectOptions(),
        offsets={c.name: c.offset for c in result.cameras},
        lens=result.lens,
        inlier_px=result.inlier_px,
        focal_sigma=result.focal_sigma,
        focals={c.name: float(c.K[0, 0]) for c in result.cameras} if result.focal_sigma is not None else None,
    )
    for fold in range(FOLDS):
        try:
            fold_tracks = _fold(tracks, videos, fold)
            if solve is None:
                part = calibrate_from_subject(fold_tracks, videos, fold_options)
            else:
                part = solve(fold_tracks, fold_options)
        except SubjectCalibrationError as error:
            failures.append(f"fold {fold + 1}: {error}")
            continue
        common = [c for c in part.cameras if any(w.name == c.name for w in result.cameras)]
        if len(common) >= 3:
            for name, (centre, angle) in _robust_errors(common, result.cameras, spread).items():
                out.centre_folds.setdefault(name, []).append(centre)
                out.rotation_folds.setdefault(name, []).append(angle)
                verified.add(name)
        elif len(common) == 2:
            a, b = (next(w for w in result.cameras if w.name == c.name) for c in common)
            angle = _angle(common[1].R @ common[0].R.T @ (b.R @ a.R.T).T)
            for name in (a.name, b.name):
                out.rotation_folds.setdefault(name, []).append(angle)
                verified.add(name)
    unverified = [c.name for c in result.cameras if c.name not in verified]
    if unverified:
        out.checked = False
        out.why_unchecked = f"{', '.join(unverified)}: no fold of the tracks poses them alone" + (
            f" ({failures[0]})" if failures else ""
        )
        log.warning("subject path: poses unverified: %s", out.why_unchecked)
        for name in unverified:
            # A pose that two thirds of the same tracks cannot reproduce is not determined by them.
            out.unstable[name] = (
                "not verified: no fold of the tracks (two thirds of them) poses it"
                + (f" ({failures[0]})" if failures else "")
                + "; track more points or a longer, more varied motion, or give --intrinsics"
            )
    for name, values in out.centre_folds.items():
        if max(values) > MAX_CENTRE and name not in out.unstable:
            out.unstable[name] = (
                f"not determined by the tracks: its centre moves by {_listed([100 * v for v in values], ' %')} of the "
                f"camera spread between folds of the data and the whole "
                f"(> {100 * MAX_CENTRE:.0f} %{_most(values, MAX_CENTRE)})"
            )
    for name, values in out.rotation_folds.items():
        if max(values) > MAX_ROTATION_DEG and name not in out.unstable:
            out.unstable[name] = (
                f"not determined by the tracks: its rotation moves by {_listed(values, ' deg')} between folds of the "
                f"data and the whole (> {MAX_ROTATION_DEG:g} deg{_most(values, MAX_ROTATION_DEG)})"
            )
    return out


def pair_without_intrinsics(videos: list[SubjectVideo]) -> bool:
    """Two cameras of which one has a self-calibrated focal (TWO_SELF_CALIBRATED): not a group to trust alone."""
    return len(videos) == 2 and any(v.K is None for v in videos)


def _most(values: list[float], limit: float) -> str:
    return f" in {sum(v > limit for v in values)} of {len(values)} folds"


def _listed(values: list[float], unit: str) -> str:
    return ", ".join(f"{v:.1f}" for v in values) + unit


def _robust_errors(
    part: list[SubjectCamera], whole: list[SubjectCamera], spread: float
) -> dict[str, tuple[float, float]]:
    """Per camera of `part`: centre change (fraction of `spread`) and rotation change (deg) from `whole`, after
    the similarity that most cameras agree with: fitted on every three cameras, the one with the most cameras
    within the tolerances kept and fitted again on those. One camera a fold poses badly then spoils no other's
    comparison (a similarity on all of them would carry its error to every camera)."""
    reference = {c.name: c for c in whole}
    best: tuple[int, float, list[SubjectCamera]] | None = None
    triples = list(itertools.combinations(part, 3))
    if len(triples) > MAX_TRIPLES:  # an even sample over all cameras (the first ones would favour the first cameras)
        pick = np.random.default_rng(0).choice(len(triples), MAX_TRIPLES, replace=False)
        triples = [triples[i] for i in sorted(pick)]
    for triple in triples:
        errors = _errors_after(part, list(triple), reference, spread)
        inside = [c for c in part if errors[c.name][0] <= MAX_CENTRE and errors[c.name][1] <= MAX_ROTATION_DEG]
        score = sum(e[0] / MAX_CENTRE + e[1] / MAX_ROTATION_DEG for e in errors.values())
        if best is None or (len(inside), -score) > (best[0], -best[1]):
            best = (len(inside), score, inside if len(inside) >= 3 else list(triple))
    assert best is not None
    return _errors_after(part, best[2], reference, spread)


def _errors_after(
    part: list[SubjectCamera], fit: list[SubjectCamera], reference: dict[str, SubjectCamera], spread: float
) -> dict[str, tuple[float, float]]:
    """Errors of every camera of `part` after the similarity fitted on `fit` (sfm.evaluate.compare's)."""
    aligned = compare(_as_cameras(fit), _as_cameras(list(reference.values())))
    out = {}
    for c in part:
        ref = reference[c.name]
        centre = aligned.scale * aligned.rotation @ c.centre + aligned.translation
        out[c.name] = (
            float(np.linalg.norm(centre - ref.centre)) / spread,
            _angle(c.R @ aligned.rotation.T @ ref.R.T),
        )
    return out


def _angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


__all__ = ["Stability", "check_stability", "pair_without_intrinsics"]
