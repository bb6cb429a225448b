"""Carry manual labels through every frame of one video: what the labeling page's "track" button calls.

For each point, a forward sweep starts at every visible label and runs until the point's next label (of any
kind), a backward sweep does the same in reverse, and the two are combined per frame (`Blend`). A track stops,
leaving the point unobserved, when a step fails (LK's forward-backward check and, if enabled, the CSRT
fallback) or when the patch at the tracked position no longer looks like the patch at the label (occlusion,
drift). Labels always win: a labeled frame returns the label, and every label starts new tracks.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from tracking.frames import FrameSource
from tracking.options import Blend, Method, TrackOptions
from tracking.steps import brightness, csrt_step, lk_step, ncc, normalize_brightness, patch_at
from tracking.tracks import SOURCE_LABEL, SOURCE_TRACK

log = logging.getLogger(__name__)

MIN_NCC = 0.5  # normalized cross-correlation with the label's patch below which the track stops
AGREE_PX = 3.0  # forward and backward tracks farther apart than this (pixels) disagree: keep the likelier one
FALLBACK_BOX_PX = 48  # side of the CSRT box around the point (the marker should fit in it)
MARGIN_PX = 2.0  # a point closer than this to the image border stops (it is leaving the frame)

# point -> frame -> (x, y), or None where the user marked the point "not visible here"
Labels = Mapping[str, Mapping[int, tuple[float, float] | None]]


class TrackedPoint(NamedTuple):
    x: float
    y: float
    score: float  # in [0, 1]; 1 for labels
    source: str  # "label" or "track"


@dataclass
class _Track:
    """A point being carried by one sweep."""

    xy: np.ndarray  # (2,)
    template: np.ndarray  # (patch, patch) float32, the patch at the label
    score: float
    frames: list[int] = field(default_factory=list)  # frames it has written to the sweep's output


# per point: frame -> (x, y, score) of one sweep
_Sweep = dict[str, dict[int, tuple[float, float, float]]]
# per point: for each track that reached the point's next label more than `AGREE_PX` away from it, its frames
# in the order it visited them
_Failed = dict[str, list[list[int]]]


def track_video(
    frames: FrameSource,
    labels: Labels,
    options: TrackOptions | None = None,
    *,
    progress: Callable[[int, int], None] | None = None,
    name: str = "video",
) -> dict[str, dict[int, TrackedPoint]]:
    """Propagate `labels` through `frames` (of the video `name`, for messages).

    Returns point -> frame -> `TrackedPoint`, with every visible label (`source="label"`, score 1) and the
    tracked positions (`source="track"`) whose score is at least `options.min_score`. Frames where a point is
    marked not visible, lost, or out of reach of any label are absent. Labels outside the video's frames are
    ignored with a warning. `progress(done, total)` is called after each frame of each of the two sweeps.
    """
    options = options or TrackOptions()
    num_frames = len(frames)
    clean: dict[str, dict[int, np.ndarray | None]] = {}
    outside: list[int] = []
    for point, by_frame in labels.items():
        clean[point] = {}
        for frame, xy in by_frame.items():
            if not 0 <= int(frame) < num_frames:
                outside.append(int(frame))
                continue
            clean[point][int(frame)] = None if xy is None else np.asarray(xy, dtype=float).reshape(2)
    if outside:  # one line, not one per label: a labels file of a longer video has hundreds
        log.warning(
            "%s: %d label(s) on frames %d-%d are outside the video's %d frames; ignored (labels of another or a "
            "longer video?)",
            name,
            len(outside),
            min(outside),
            max(outside),
            num_frames,
        )
    total = 2 * num_frames
    done = [0]

    def tick() -> None:
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    forward, failed_forward = _sweep(frames, clean, options, +1, tick)
    backward, failed_backward = _sweep(frames, clean, options, -1, tick)
    if not options.closure_check:
        return _combine(clean, forward, backward, options, num_frames)
    # A track that arrives at the next label far from it drifted somewhere on the way: its positions count only
    # where the track from the other side confirms them.
    confirmed_forward = _confirmed_only(forward, failed_forward, backward, options)
    confirmed_backward = _confirmed_only(backward, failed_backward, forward, options)
    _say_unconfirmed(name, forward, backward, confirmed_forward, confirmed_backward)
    return _combine(clean, confirmed_forward, confirmed_backward, options, num_frames)


def _say_unconfirmed(name: str, forward: _Sweep, backward: _Sweep, kept_forward: _Sweep, kept_backward: _Sweep) -> None:
    """One warning per point whose tracked frames the closure check dropped, with the frames and how far apart the
    two sweeps were there: a label placed on another spot of the point (a drag correction) drops a whole stretch."""
    for point in sorted(set(forward) | set(backward)):
        fwd, bwd = forward.get(point, {}), backward.get(point, {})
        kept = set(kept_forward.get(point, {})) | set(kept_backward.get(point, {}))
        dropped = sorted((set(fwd) | set(bwd)) - kept)
        if not dropped:
            continue
        apart = [
            float(np.hypot(*(np.asarray(fwd[f][:2]) - np.asarray(bwd[f][:2]))))
            for f in dropped
            if f in fwd and f in bwd
        ]
        how = f"median {np.median(apart):.0f} px apart" if apart else "one side lost it"
        log.warning(
            "%s: point %r: tracked frames %s dropped: the tracks from its labels on either side disagree there (%s, "
            "over %g px): one drifted, or the labels mark different spots of it; look at those frames in `dynrecon "
            "label` and move a label or add one between (or `dynrecon track --no-closure-check`)",
            name,
            point,
            _runs(dropped),
            how,
            AGREE_PX,
        )


def _runs(frames: list[int], shown: int = 3) -> str:
    """'1-59, 70-72' for sorted frames, the first `shown` runs."""
    runs: list[list[int]] = []
    for frame in frames:
        if runs and frame == runs[-1][1] + 1:
            runs[-1][1] = frame
        else:
            runs.append([frame, frame])
    text = ", ".join(f"{a}-{b}" if b > a else str(a) for a, b in runs[:shown])
    return text + (f" and {len(runs) - shown} more stretch(es)" if len(runs) > shown else "")


def _confirmed_only(sweep: _Sweep, failed: _Failed, other: _Sweep, options: TrackOptions) -> _Sweep:
    kept = {point: dict(by_frame) for point, by_frame in sweep.items()}
    for point, tracks in failed.items():
        theirs = other.get(point, {})
        for visited in tracks:
            agree = [
                i
                for i, frame in enumerate(visited)
                if frame in theirs
                and np.hypot(sweep[point][frame][0] - theirs[frame][0], sweep[point][frame][1] - theirs[frame][1])
                <= AGREE_PX
            ]
            # Drift grows along a track: trust it up to the last frame the other side confirms, not after.
            for frame in visited[agree[-1] + 1 if agree else 0 :]:
                kept[point].pop(frame, None)
    return kept


def _sweep(
    frames: FrameSource,
    labels: dict[str, dict[int, np.ndarray | None]],
    options: TrackOptions,
    direction: int,
    tick: Callable[[], None],
) -> tuple[_Sweep, _Failed]:
    """One pass over the frames in `direction` (+1 forward, -1 backward), all points at once."""
    num_frames = len(frames)
    out: _Sweep = {point: {} for point in labels}
    failed: _Failed = {point: [] for point in labels}
    by_frame: dict[int, dict[str, np.ndarray | None]] = {}
    for point, marks in labels.items():
        for frame, xy in marks.items():
            by_frame.setdefault(frame, {})[point] = xy
    order = range(0)
    if by_frame:
        order = range(min(by_frame), num_frames) if direction > 0 else range(max(by_frame), -1, -1)
    for _ in range(num_frames - len(order)):  # frames no track can reach still count as done
        tick()
    active: dict[str, _Track] = {}
    prev: np.ndarray | None = None
    reference: tuple[float, float] | None = None
    for frame in order:
        here = by_frame.get(frame, {})
        if not active and not any(xy is not None for xy in here.values()):
            prev = None
            tick()
            continue
        gray = frames.gray(frame)
        if options.normalize:
            # Every frame of the sweep gets the brightness of the first one it decoded.
            reference = reference or brightness(gray)
            gray = normalize_brightness(gray, reference)
        if active and prev is not None:
            _advance(prev, gray, active, options, out, frame)
        for name, label in here.items():
            # A label of any kind ends the track arriving here; the label itself may start the next one.
            arriving = active.pop(name, None)
            if arriving is not None:
                reached = out[name].pop(frame)
                arriving.frames.pop()
                miss = np.inf if label is None else np.hypot(reached[0] - label[0], reached[1] - label[1])
                if label is not None and miss > AGREE_PX:
                    failed[name].append(arriving.frames)
            if label is not None:
                template = patch_at(gray, label, options.patch)
                active[name] = _Track(xy=label.copy(), template=template, score=1.0)
        prev = gray
        tick()
    return out, failed


def _advance(
    prev: np.ndarray, cur: np.ndarray, active: dict[str, _Track], options: TrackOptions, out: _Sweep, frame: int
) -> None:
    """Move every active track from `prev` to `cur`; record survivors in `out[point][frame]`, drop others."""
    names = list(active)
    xy0 = np.array([active[n].xy for n in names]).reshape(-1, 2)
    if options.method is Method.CSRT:
        xy1, fb = np.full_like(xy0, np.nan), np.full(len(names), np.inf)
    else:
        xy1, fb = lk_step(prev, cur, xy0, options)
    for i, name in enumerate(names):
        track = active[name]
        step = None if options.method is Method.CSRT else _accept(cur, xy1[i], float(fb[i]), track, options)
        if step is None and options.method is not Method.LK:
            # LK failed its own check or landed on something that does not look like the label: try CSRT.
            step = _fallback(prev, cur, xy0[i], track, options)
        if step is None:
            log.debug("%s frame %d: stopped (fb %.2f px)", name, frame, fb[i])
            del active[name]
            continue
        track.xy = step[0]
        track.score = min(step[1], track.score) if options.score_memory else step[1]
        out[name][frame] = (float(track.xy[0]), float(track.xy[1]), track.score)
        track.frames.append(frame)


def _accept(
    cur: np.ndarray, xy: np.ndarray, fb: float, track: _Track, options: TrackOptions, penalty: float = 1.0
) -> tuple[np.ndarray, float] | None:
    """The new position and its score, or None when the step fails the forward-backward check, leaves the
    picture, or the patch there no longer looks like the label's."""
    height, width = cur.shape[:2]
    m = MARGIN_PX
    if not (fb <= options.fb_threshold and m <= xy[0] <= width - 1 - m and m <= xy[1] <= height - 1 - m):
        return None
    similarity = ncc(patch_at(cur, xy, options.patch), track.template)
    s_app = (similarity - MIN_NCC) / (1.0 - MIN_NCC)
    if s_app <= 0.0:
        return None
    s_fb = 1.0 - 0.5 * fb / options.fb_threshold
    return xy.copy(), float(np.clip(min(s_app, 1.0) * s_fb * penalty, 0.0, 1.0))


def _fallback(
    prev: np.ndarray, cur: np.ndarray, xy0: np.ndarray, track: _Track, options: TrackOptions
) -> tuple[np.ndarray, float] | None:
    """One CSRT step around the point, refined by LK from CSRT's answer."""
    guess = csrt_step(prev, cur, xy0, FALLBACK_BOX_PX)
    if guess is None:
        return None
    refined, fb = lk_step(prev, cur, xy0.reshape(1, 2), options, guess=guess.reshape(1, 2))
    if np.linalg.norm(refined[0] - guess) < 0.5 * options.win_size:
        step = _accept(cur, refined[0], float(fb[0]), track, options)
        if step is not None:
            return step
    if options.accept_unrefined:
        # CSRT alone: integer precision and no consistency check, so it counts for less.
        return _accept(cur, guess, 0.5 * options.fb_threshold, track, options, penalty=0.5)
    return None


def _combine(
    labels: dict[str, dict[int, np.ndarray | None]],
    forward: _Sweep,
    backward: _Sweep,
    options: TrackOptions,
    num_frames: int,
) -> dict[str, dict[int, TrackedPoint]]:
    result: dict[str, dict[int, TrackedPoint]] = {}
    for point, marks in labels.items():
        anchors = sorted(marks)
        visible = [f for f in anchors if marks[f] is not None]
        first_visible = visible[0] if visible else num_frames
        fwd, bwd = forward.get(point, {}), backward.get(point, {})
        merged: dict[int, TrackedPoint] = {}
        for frame in sorted(set(fwd) | set(bwd)):
            f = fwd.get(frame)
            b = bwd.get(frame)
            if options.blend is Blend.FORWARD and frame > first_visible:
                b = None
            chosen = _blend(f, b, frame, anchors, options)
            if chosen is not None and chosen[2] >= options.min_score:
                merged[frame] = TrackedPoint(chosen[0], chosen[1], chosen[2], SOURCE_TRACK)
        for frame, xy in marks.items():
            merged.pop(frame, None)
            if xy is not None:
                merged[frame] = TrackedPoint(float(xy[0]), float(xy[1]), 1.0, SOURCE_LABEL)
        result[point] = dict(sorted(merged.items()))
    return result


def _blend(
    f: tuple[float, float, float] | None,
    b: tuple[float, float, float] | None,
    frame: int,
    anchors: list[int],
    options: TrackOptions,
) -> tuple[float, float, float] | None:
    if f is None or b is None:
        return f if b is None else b
    # Drift grows with the distance from the label a track started at: weight each by closeness to its label.
    before = max((a for a in anchors if a < frame), default=frame - 1)
    after = min((a for a in anchors if a > frame), default=frame + 1)
    closeness_f = (after - frame) / (after - before)
    closeness_b = (frame - before) / (after - before)
    wf, wb = closeness_f * f[2], closeness_b * b[2]
    distance = float(np.hypot(f[0] - b[0], f[1] - b[1]))
    better = f if wf >= wb else b
    if distance > AGREE_PX:
        # One of them drifted: keep the likelier one, with a score that says it is a guess.
        return better[0], better[1], better[2] * AGREE_PX / distance
    score = 1.0 - (1.0 - f[2]) * (1.0 - b[2])  # two tracks that agree are more certain than either
    if options.blend is Blend.BEST:
        return better[0], better[1], score
    if wf + wb <= 0.0:
        return better[0], better[1], score
    x = (wf * f[0] + wb * b[0]) / (wf + wb)
    y = (wf * f[1] + wb * b[1]) / (wf + wb)
    return x, y, score
