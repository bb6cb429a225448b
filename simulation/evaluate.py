"""Accuracy of reconstructed points against ground truth, as in the paper: the share of points whose Euclidean
error is below 10, 20, 30, 40, 50 and 100 mm.

Rows are matched by (video, frame, point). Every row of the truth must be in the estimate and vice versa:
a missing or unknown row is an InputError, never a silent skip. A point the estimate left empty (NaN) counts
as a failure at every threshold. Truth rows without a position (NaN) are not scored, only counted.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from reconstruct.outputs.points import FramePoints, read_points

log = logging.getLogger(__name__)

THRESHOLDS_MM = (10.0, 20.0, 30.0, 40.0, 50.0, 100.0)


@dataclass(kw_only=True)
class ReconstructionAccuracy:
    """Shares of points under each error threshold, and the errors themselves (`evaluate`)."""

    thresholds: tuple[float, ...]  # in the units of the files (mm for simulations)
    share_under: np.ndarray  # (K,) fraction of scored points with error < threshold (failures count as above)
    share_under_observed: np.ndarray  # (K,) the same over points the truth marks observed (NaN if none)
    share_under_unobserved: np.ndarray  # (K,) ... and over unobserved ones (NaN if none)
    median: float  # over every scored point, failures as +inf
    mean: float  # over the reconstructed points only (NaN if none)
    count: int  # scored points: (frame, point) rows with a truth position
    unreconstructed: int  # scored points the estimate left empty
    no_truth: int  # rows without a truth position, not scored
    errors: np.ndarray  # (count,) Euclidean errors, +inf where unreconstructed

    def table(self) -> str:
        """One line: the shares under each threshold, median, mean and failures."""
        cells = [f"<{t:g}: {100 * s:6.2f}%" for t, s in zip(self.thresholds, self.share_under, strict=True)]
        return (
            " | ".join(cells) + f" | median {self.median:.2f} | mean {self.mean:.2f} | "
            f"unreconstructed {self.unreconstructed}/{self.count}"
        )

    def as_dict(self) -> dict[str, object]:
        """JSON-ready numbers (NaN and inf as null)."""
        return {
            "thresholds": list(self.thresholds),
            "share_under": _json_list(self.share_under),
            "share_under_observed": _json_list(self.share_under_observed),
            "share_under_unobserved": _json_list(self.share_under_unobserved),
            "median": _json_number(self.median),
            "mean": _json_number(self.mean),
            "count": self.count,
            "unreconstructed": self.unreconstructed,
            "no_truth": self.no_truth,
        }


def _json_number(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _json_list(values: np.ndarray) -> list[float | None]:
    return [_json_number(v) for v in values]


def _shares(errors: np.ndarray, thresholds: tuple[float, ...]) -> np.ndarray:
    if errors.size == 0:
        return np.full(len(thresholds), np.nan)
    return np.array([float(np.mean(errors < t)) for t in thresholds])


def evaluate(
    estimate: FramePoints,
    truth: FramePoints,
    thresholds: tuple[float, ...] = THRESHOLDS_MM,
    *,
    estimate_path: Path | None = None,
    truth_path: Path | None = None,
) -> ReconstructionAccuracy:
    """Compare `estimate` with `truth` row by row; both must have the same (video, frame) rows and points."""
    if not thresholds or any(not t > 0 for t in thresholds):
        raise InputError(None, f"thresholds must be positive numbers, got {thresholds}")
    truth_rows = truth.index()
    estimate_rows = estimate.index()
    for key in estimate_rows:
        if key not in truth_rows:
            raise InputError(
                estimate_path,
                f"video {key[0]!r} frame {key[1]} is not in the truth",
                fix=f"evaluate against the truth of the same capture ({truth_path or 'truth'})",
            )
    # a video without one row was left out of the solve (report.json temporal.left_out): its rows are unreconstructed
    solved_videos = set(estimate.videos)
    for key in truth_rows:
        if key not in estimate_rows and key[0] in solved_videos:
            raise InputError(
                estimate_path,
                f"video {key[0]!r} frame {key[1]} of the truth has no row",
                fix="the estimate must have one row for every posed frame and point",
            )
    left_out = sorted(set(truth.videos) - solved_videos)
    if left_out:
        log.warning(
            "video(s) %s have no rows in the estimate (left out of the solve): their truth rows count as "
            "unreconstructed",
            ", ".join(left_out),
        )
    extra_points = sorted(set(estimate.point_names) - set(truth.point_names))
    if extra_points:
        raise InputError(
            estimate_path,
            f"point {extra_points[0]!r} is not in the truth",
            fix=f"evaluate against the truth of the same capture ({truth_path or 'truth'})",
        )
    estimate_points = {name: i for i, name in enumerate(estimate.point_names)}
    lacking = [name for name in truth.point_names if name not in estimate_points]
    if lacking:
        raise InputError(
            estimate_path,
            f"point {lacking[0]!r} of the truth has no rows",
            fix="the estimate must have one row for every posed frame and point",
        )

    # Estimate rearranged into the truth's frame and point order.
    frame_order = np.array([estimate_rows.get(key, -1) for key in truth_rows], dtype=np.int64)
    point_order = np.array([estimate_points[name] for name in truth.point_names], dtype=np.int64)
    guess = estimate.xyz[frame_order][:, point_order]  # (F, P, 3)
    guess[frame_order < 0] = np.nan
    has_truth = np.isfinite(truth.xyz).all(axis=2)  # (F, P)
    reconstructed = np.isfinite(guess).all(axis=2)
    errors_fp = np.where(reconstructed, np.linalg.norm(np.nan_to_num(guess - truth.xyz), axis=2), np.inf)
    errors = errors_fp[has_truth]
    observed = truth.observed[has_truth]
    finite = errors[np.isfinite(errors)]
    accuracy = ReconstructionAccuracy(
        thresholds=tuple(float(t) for t in thresholds),
        share_under=_shares(errors, thresholds),
        share_under_observed=_shares(errors[observed], thresholds),
        share_under_unobserved=_shares(errors[~observed], thresholds),
        median=float(np.median(errors)) if errors.size else float("nan"),
        mean=float(finite.mean()) if finite.size else float("nan"),
        count=int(errors.size),
        unreconstructed=int((~np.isfinite(errors)).sum()),
        no_truth=int((~has_truth).sum()),
        errors=errors,
    )
    if accuracy.no_truth:
        log.info("%d row(s) have no truth position and were not scored", accuracy.no_truth)
    if accuracy.count == 0:
        raise InputError(truth_path, "no row has a truth position", fix="check the truth file")
    return accuracy


def run(
    directory: str | Path, truth_path: str | Path | None = None, thresholds: tuple[float, ...] = THRESHOLDS_MM
) -> ReconstructionAccuracy:
    """Score `DIR/points3d.csv` against `DIR/truth.csv` (or `truth_path`)."""
    directory = Path(directory)
    estimate_path = directory / "points3d.csv"
    truth_file = Path(truth_path) if truth_path is not None else directory / "truth.csv"
    if not estimate_path.is_file():
        raise InputError(
            estimate_path,
            "file not found",
            fix="run `dynrecon solve --out DIR` first, or give the folder of points3d.csv",
        )
    if not truth_file.is_file():
        raise InputError(
            truth_file,
            "file not found",
            fix="give the simulation's truth.csv with --truth or put it beside points3d.csv",
        )
    return evaluate(
        read_points(estimate_path),
        read_points(truth_file),
        thresholds,
        estimate_path=estimate_path,
        truth_path=truth_file,
    )
