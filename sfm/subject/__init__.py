"""Calibration of static cameras from a moving subject's 2D tracks (no board, no synchronization).

Each video is one fixed camera. Pairs of videos give a time offset and an epipolar geometry; chained offsets, a
spanning set of poses and a bundle adjustment over poses, offsets, unknown focals and the subject's trajectory follow.
"""

from __future__ import annotations

from sfm.subject.calibrate import calibrate_from_subject
from sfm.subject.model import (
    Lens,
    NoiseTrial,
    PairResult,
    SubjectCalibrationError,
    SubjectCamera,
    SubjectOptions,
    SubjectResult,
    SubjectVideo,
)
from sfm.subject.noise import choose_noise

__all__ = [
    "Lens",
    "NoiseTrial",
    "PairResult",
    "SubjectCalibrationError",
    "SubjectCamera",
    "SubjectOptions",
    "SubjectResult",
    "SubjectVideo",
    "calibrate_from_subject",
    "choose_noise",
]
