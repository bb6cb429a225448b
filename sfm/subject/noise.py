"""Which noise scale do the tracks support? Solve at each of NOISE_SCALES_PX and keep the most reproducible poses.

A RANSAC threshold made for marker-grade tracks (clicks, tracked labels, board corners: about a pixel) discards most
of a pose detector's keypoints, which scatter several pixels around any one 3D point (a joint's centre shifts with
the view); the poses then rest on whichever subset happened to agree and change from one part of the data to the
next. A wider threshold lets marker-grade tracks' outliers in. The median residual cannot tell the two apart (a
narrower threshold always fits its own inliers closer), nor, measured on detector keypoints, can the held-out
reprojection error (dominated by the keypoints' own scatter); the folds of `check_stability` can: the scale whose
poses the folds of the data reproduce best is kept, the first (marker-grade) one unless a wider one is clearly better.
The scales are solved side by side (`dynrecon.beside`: a forked process on another core where that is safe): each
solve is self-contained (its own seeded random draws), so the result is the same as one after the other.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import re
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from dynrecon.beside import beside
from sfm.subject.calibrate import calibrate_from_subject
from sfm.subject.model import (
    NOISE_SCALES_PX,
    NoiseTrial,
    ScalePointsError,
    SubjectCalibrationError,
    SubjectOptions,
    SubjectResult,
    SubjectVideo,
)
from sfm.subject.stability import Stability, check_stability
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

T = TypeVar("T")  # what a trial returns besides its result and folds (the posed videos' alignment)

SPREAD_GAIN = 0.8  # a wider scale replaces the first where its folds' rotation change is this much smaller


def choose_noise(
    tracks: Tracks, videos: list[SubjectVideo], options: SubjectOptions | None = None
) -> tuple[SubjectResult, Stability]:
    """`calibrate_from_subject` and its `check_stability`, at `options.inlier_px` or, when None, at the scale of
    NOISE_SCALES_PX whose poses the folds reproduce (`choose_scale`)."""

    def trial(scaled: SubjectOptions) -> tuple[SubjectResult, Stability, None]:
        result = calibrate_from_subject(tracks, videos, scaled)
        return result, check_stability(tracks, videos, result, scaled), None

    result, stability, _ = choose_scale(trial, options or SubjectOptions())
    return result, stability


def choose_scale(
    trial: Callable[[SubjectOptions], tuple[SubjectResult, Stability, T]], options: SubjectOptions
) -> tuple[SubjectResult, Stability, T]:
    """`trial` (a subject-path solve and its folds) at `options.inlier_px` or, when None, at each of
    NOISE_SCALES_PX: a wider scale is kept where it leaves more cameras stable, or the same number whose rotation
    changes between a fold and the whole (median over the cameras) are SPREAD_GAIN times the first's.
    `result.noise_check` says what each scale gave."""
    if options.inlier_px is not None:
        return trial(options)
    tried: dict[float, tuple[SubjectResult, Stability, T]] = {}
    errors: dict[float, SubjectCalibrationError] = {}
    first, *wider = NOISE_SCALES_PX
    with contextlib.ExitStack() as stack:
        running = [
            stack.enter_context(beside(_attempt, trial, dataclasses.replace(options, inlier_px=px))) for px in wider
        ]
        outcomes = [_attempt(trial, dataclasses.replace(options, inlier_px=first))] + [r.result() for r in running]
    if running:
        how = "forked" if all(r.forked for r in running) else "one after the other" if running[0].inline else "threads"
        log.info("noise scales solved side by side (%s)", how)
    for px, outcome in zip(NOISE_SCALES_PX, outcomes, strict=True):
        if isinstance(outcome, SubjectCalibrationError):  # ScalePointsError too: another scale may triangulate the pair
            errors[px] = outcome
        else:
            tried[px] = outcome
    if not tried:
        # a scale whose poses stood but not its scale pair first (the caller may solve again without the pair)
        main = next((e for e in errors.values() if isinstance(e, ScalePointsError)), errors[NOISE_SCALES_PX[0]])
        # another scale's error that differs only in its numbers (the scale's px) adds nothing
        others = "; ".join(
            f"at {px:g} px: {e}" for px, e in errors.items() if e is not main and _wording(e) != _wording(main)
        )
        raise type(main)(f"{main} ({others})" if others else str(main)) from main
    chosen = min(tried)
    for px in sorted(tried):
        if px != chosen and _better(tried[px][:2], tried[chosen][:2]):
            chosen = px
    check = {px: NoiseTrial(failed=str(e)) for px, e in errors.items()}
    for px, (result, stability, _) in tried.items():
        stable = stable_cameras(result, stability)
        check[px] = NoiseTrial(
            posed=len(result.cameras), stable=len(stable), fold_rotation_deg=_spread(stability, stable)
        )
    log.info(
        "noise scale: %g px of %s (%s)",
        chosen,
        ", ".join(f"{px:g}" for px in NOISE_SCALES_PX),
        "; ".join(f"{px:g} px: {entry.to_json()}" for px, entry in sorted(check.items())),
    )
    kept = tried[chosen]
    kept[0].noise_check = dict(sorted(check.items()))
    return kept


def _attempt(
    trial: Callable[[SubjectOptions], tuple[SubjectResult, Stability, T]], options: SubjectOptions
) -> tuple[SubjectResult, Stability, T] | SubjectCalibrationError:
    """The trial's outcome, its refusal included (a value, so that one scale's refusal leaves the others' solves)."""
    try:
        return trial(options)
    except SubjectCalibrationError as error:
        return error


def stable_cameras(result: SubjectResult, stability: Stability) -> list[str]:
    return [c.name for c in result.cameras if c.name not in stability.unstable]


def _spread(stability: Stability, names: list[str]) -> float:
    """The median over `names` of each camera's largest rotation change (deg) between a fold and the whole (inf
    when none was compared): the median, since one camera's worst fold is a noisy statistic."""
    largest = stability.rotation_deg
    values = [largest[n] for n in names if n in largest]
    return float(np.median(values)) if values else float("inf")


def _better(wide: tuple[SubjectResult, Stability], first: tuple[SubjectResult, Stability]) -> bool:
    """Whether the wider scale's poses are the more reproducible."""
    stable_wide, stable_first = stable_cameras(*wide), stable_cameras(*first)
    if len(stable_wide) != len(stable_first):
        return len(stable_wide) > len(stable_first)
    return _spread(wide[1], stable_wide) < SPREAD_GAIN * _spread(first[1], stable_first)


def _wording(error: Exception) -> str:
    """An error's text without its numbers."""
    return re.sub(r"\d+(\.\d+)?", "#", str(error))
