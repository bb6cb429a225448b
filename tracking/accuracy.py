"""Score tracks against rendered ground truth (`tracking.synthetic`): pixel error where the point is visible,
and whether the tracker gave up where it is hidden."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tracking.propagate import Labels, TrackedPoint
from tracking.synthetic import SyntheticVideo
from tracking.tracks import SOURCE_LABEL


def labels_every(video: SyntheticVideo, step: int, offset: int = 0) -> Labels:
    """Ground-truth labels on frames offset, offset+step, ...; a hidden point gets a "not visible" label."""
    labels: dict[str, dict[int, tuple[float, float] | None]] = {}
    for p, name in enumerate(video.names):
        labels[name] = {}
        for f in range(offset, len(video.uv), step):
            x, y = video.uv[f, p]
            labels[name][f] = (float(x), float(y)) if video.visible[f, p] else None
    return labels


@dataclass(kw_only=True)
class Accuracy:
    errors: np.ndarray  # (K,) pixel errors of tracked positions where the point is visible
    visible: int  # unlabeled (frame, point) pairs where the point is visible
    hidden: int  # unlabeled (frame, point) pairs where the point is hidden (occluded or outside the picture)
    gave_up: int  # of the hidden pairs, those the tracker left unobserved

    @property
    def median(self) -> float:
        return float(np.median(self.errors)) if len(self.errors) else float("nan")

    @property
    def p95(self) -> float:
        return float(np.percentile(self.errors, 95)) if len(self.errors) else float("nan")

    @property
    def coverage(self) -> float:
        """Share of visible unlabeled pairs that got a tracked position."""
        return len(self.errors) / self.visible if self.visible else float("nan")

    @property
    def gave_up_share(self) -> float:
        return self.gave_up / self.hidden if self.hidden else float("nan")

    def row(self) -> str:
        return (
            f"{self.median:.3f} | {self.p95:.3f} | {np.max(self.errors, initial=0):.2f} | "
            f"{100 * self.coverage:.1f}% | {100 * self.gave_up_share:.1f}% "
            f"({self.gave_up}/{self.hidden})"
        )


def score(result: dict[str, dict[int, TrackedPoint]], video: SyntheticVideo) -> Accuracy:
    errors: list[float] = []
    visible = hidden = gave_up = 0
    for p, name in enumerate(video.names):
        by_frame = result.get(name, {})
        for f in range(len(video.uv)):
            tracked = by_frame.get(f)
            if tracked is not None and tracked.source == SOURCE_LABEL:
                continue
            if video.visible[f, p]:
                visible += 1
                if tracked is not None:
                    x, y = video.uv[f, p]
                    errors.append(float(np.hypot(tracked.x - x, tracked.y - y)))
            else:
                hidden += 1
                gave_up += tracked is None
    return Accuracy(errors=np.array(errors), visible=visible, hidden=hidden, gave_up=gave_up)
