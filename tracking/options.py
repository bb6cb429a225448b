"""Options of the label propagation (`tracking.propagate.track_video`) and of `dynrecon track`."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class Method(enum.Enum):
    """How a point is carried from one frame to the next."""

    LK = "lk"  # pyramidal Lucas-Kanade with a forward-backward check; the track stops where LK fails
    LK_CSRT = "lk+csrt"  # LK; where it fails, one CSRT step on a patch around the point, refined by LK
    CSRT = "csrt"  # CSRT for every step, refined by LK where LK agrees (slow; for comparison)


class Blend(enum.Enum):
    """How the forward track (from the earlier label) and the backward one (from the later label) combine."""

    # mean weighted by score and by closeness to each label; the better one where they disagree
    WEIGHTED = "weighted"
    BEST = "best"  # the one with the higher score x closeness
    FORWARD = "forward"  # forward only (backward only before a point's first label); the baseline


MAX_WINDOW = 401  # pixels: beyond a window of a whole frame's side, only memory is spent


@dataclass(kw_only=True)
class TrackOptions:
    """What the CLI, the pipeline and the benchmarks vary; the fixed constants are in `tracking.propagate` and
    `tracking.steps`."""

    method: Method = Method.LK  # as accurate as LK_CSRT on every rendered scenario, and faster
    blend: Blend = Blend.WEIGHTED
    normalize: bool = True  # cancel global brightness changes (auto exposure) before tracking
    win_size: int = 21  # LK window side, pixels
    fb_threshold: float = 1.0  # forward-backward error (pixels) above which an LK step counts as failed
    patch: int = 21  # side of the appearance patch compared with the label's patch, pixels
    accept_unrefined: bool = False  # keep a CSRT step that LK cannot confirm (at half the score)
    closure_check: bool = True  # drop a track that reaches the next label far from it, unless confirmed
    score_memory: bool = True  # a track's score never rises again after a doubtful step (fewer drifts)
    min_score: float = 0.2  # tracked positions with a lower score are left out (unobserved)

    def __post_init__(self) -> None:
        # Programming errors (the CLI checks what users type): fail at construction, not deep inside a sweep.
        if not 0.0 <= self.min_score <= 1.0:
            raise ValueError(f"min_score {self.min_score} must be in [0, 1]")
        if self.fb_threshold <= 0.0:
            raise ValueError("fb_threshold must be positive")
        if not (5 <= self.win_size <= MAX_WINDOW and 5 <= self.patch <= MAX_WINDOW):
            raise ValueError(f"win_size and patch must be from 5 to {MAX_WINDOW}")
