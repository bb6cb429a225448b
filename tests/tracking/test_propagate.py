from __future__ import annotations

import logging
import re

import cv2
import numpy as np
import pytest

from tracking.accuracy import labels_every, score
from tracking.frames import ArrayFrames
from tracking.options import Blend, Method, TrackOptions
from tracking.propagate import track_video
from tracking.steps import brightness, normalize_brightness
from tracking.synthetic import SyntheticVideo
from tracking.tracks import SOURCE_LABEL, SOURCE_TRACK


def _frames(video: SyntheticVideo) -> ArrayFrames:
    assert video.frames is not None
    return ArrayFrames(video.frames)


def test_labels_every_tenth_frame_meet_the_acceptance_bounds(small_video: SyntheticVideo) -> None:
    result = track_video(_frames(small_video), labels_every(small_video, 10), TrackOptions())
    accuracy = score(result, small_video)
    assert accuracy.median < 1.0
    assert accuracy.p95 < 3.0
    assert accuracy.coverage > 0.85
    # The occluding bar hides markers for a few frames each: the tracker must stop there, not follow the bar.
    assert accuracy.hidden > 5
    assert accuracy.gave_up_share > 0.8
    for by_frame in result.values():
        for point in by_frame.values():
            assert 0.0 <= point.score <= 1.0
            assert point.source in (SOURCE_LABEL, SOURCE_TRACK)


def test_every_blend_is_accurate_and_blending_beats_forward_only(small_video: SyntheticVideo) -> None:
    labels = labels_every(small_video, 10)
    accuracy = {
        blend: score(track_video(_frames(small_video), labels, TrackOptions(blend=blend)), small_video)
        for blend in Blend
    }
    for blend in Blend:
        assert accuracy[blend].median < 1.0
    # Both-sided tracks halve the distance to the nearest label, so they drift less and reach more frames.
    assert accuracy[Blend.WEIGHTED].median < accuracy[Blend.FORWARD].median
    assert accuracy[Blend.WEIGHTED].coverage > accuracy[Blend.FORWARD].coverage


def test_csrt_fallback_tracks_the_same_points(small_video: SyntheticVideo) -> None:
    labels = {name: marks for name, marks in labels_every(small_video, 10).items() if name == "m0"}
    frames = ArrayFrames(small_video.frames[:11] if small_video.frames else [])
    lk = track_video(frames, labels, TrackOptions(method=Method.LK))
    for method in (Method.LK_CSRT, Method.CSRT):
        other = track_video(frames, labels, TrackOptions(method=method))
        for name in labels:
            common = set(lk[name]) & set(other[name])
            assert len(common) >= 0.8 * len(lk[name])
            gap = max(np.hypot(lk[name][f].x - other[name][f].x, lk[name][f].y - other[name][f].y) for f in common)
            assert gap < 1.0


def test_labels_win_and_reanchor(small_video: SyntheticVideo) -> None:
    uv = small_video.uv
    # A deliberately "corrected" label 0.7 px off the truth on frame 5 must come back exactly, and the frames
    # next to it must follow it (re-anchoring) rather than the label on frame 0.
    moved = (float(uv[5, 0, 0]) + 0.7, float(uv[5, 0, 1]))
    labels = {"m0": {0: (float(uv[0, 0, 0]), float(uv[0, 0, 1])), 5: moved}}
    result = track_video(_frames(small_video), labels, TrackOptions())["m0"]
    assert result[5].source == SOURCE_LABEL and (result[5].x, result[5].y) == moved and result[5].score == 1.0
    assert result[0].source == SOURCE_LABEL
    assert result[6].source == SOURCE_TRACK
    assert abs(result[6].x - (uv[6, 0, 0] + 0.7)) < 0.3  # follows the new label's offset


def test_a_hidden_label_stops_tracks_from_both_sides(small_video: SyntheticVideo) -> None:
    uv = small_video.uv
    p = int(np.flatnonzero(small_video.visible[:20].all(axis=0))[0])  # a marker visible on frames 0..19
    labels = {
        "m": {0: (float(uv[0, p, 0]), float(uv[0, p, 1])), 8: None, 16: (float(uv[16, p, 0]), float(uv[16, p, 1]))}
    }
    result = track_video(_frames(small_video), labels, TrackOptions())["m"]
    assert 8 not in result
    assert all(f in result for f in range(0, 8))  # forward from 0 up to the hidden mark
    assert result[15].source == SOURCE_TRACK  # backward from 16 towards it
    assert all(f in result for f in range(16, 20))  # forward from 16


def test_labels_outside_the_video_are_ignored_and_no_labels_give_nothing(small_video: SyntheticVideo) -> None:
    frames = _frames(small_video)
    assert track_video(frames, {}, TrackOptions()) == {}
    result = track_video(frames, {"m0": {500: (10.0, 10.0)}, "m1": {3: None}}, TrackOptions())
    assert result == {"m0": {}, "m1": {}}


def test_progress_is_reported(small_video: SyntheticVideo) -> None:
    calls: list[tuple[int, int]] = []
    track_video(
        _frames(small_video),
        {"m0": {0: tuple(small_video.uv[0, 0])}},
        TrackOptions(),
        progress=lambda done, total: calls.append((done, total)),
    )
    assert calls[-1] == (80, 80)
    assert [c[0] for c in calls] == list(range(1, 81))


def test_a_point_leaving_the_picture_stops() -> None:
    rng = np.random.default_rng(3)
    texture = (rng.random((120, 400)) * 255).astype(np.uint8)
    # The scene slides left 6 px per frame; a point at x=40 leaves the 160 px window after ~7 frames.
    frames = ArrayFrames([np.ascontiguousarray(texture[:, 6 * t : 6 * t + 160]) for t in range(20)])
    result = track_video(frames, {"p": {0: (40.0, 60.0)}}, TrackOptions())["p"]
    assert max(result) < 8
    for f, point in result.items():
        assert abs(point.x - (40.0 - 6 * f)) < 0.5 and abs(point.y - 60.0) < 0.5


def test_brightness_normalization_survives_auto_exposure_flicker() -> None:
    rng = np.random.default_rng(5)
    noise = rng.random((200, 400)).astype(np.float32)
    texture = cv2.GaussianBlur(noise, (0, 0), 2.0)
    texture = (texture - texture.mean()) / texture.std()
    frames = []
    for t in range(12):
        gain = 1.0 if t % 2 == 0 else 1.35  # every other frame 35% brighter, as auto exposure does
        window = texture[20:180, 2 * t : 2 * t + 200]
        frames.append(np.clip(gain * (110 + 30 * window), 0, 255).astype(np.uint8))
    labels = {"p": {0: (100.0, 80.0)}}
    truth = {t: (100.0 - 2 * t, 80.0) for t in range(12)}
    with_norm = track_video(ArrayFrames(frames), labels, TrackOptions())["p"]
    assert set(with_norm) == set(range(12))
    for t, point in with_norm.items():
        assert np.hypot(point.x - truth[t][0], point.y - truth[t][1]) < 0.3
    # The normalized frames themselves no longer flicker.
    reference = brightness(frames[0])
    a, b = normalize_brightness(frames[4], reference), normalize_brightness(frames[5], reference)
    assert a is frames[4]  # same exposure as the reference: untouched
    assert abs(float(a.mean()) - float(b.mean())) < 1.0 and abs(float(a.std()) - float(b.std())) < 1.0


def test_tracks_that_miss_the_next_label_are_dropped_unless_confirmed(
    small_video: SyntheticVideo, caplog: pytest.LogCaptureFixture
) -> None:
    uv = small_video.uv
    p = int(np.flatnonzero(small_video.visible[:12].all(axis=0))[0])
    # Two labels 5 px apart from what the video shows between them: each track arrives 5 px off the other
    # label, so neither can be trusted and the frames between stay unobserved.
    labels = {"m": {0: (float(uv[0, p, 0]), float(uv[0, p, 1])), 10: (float(uv[10, p, 0]) + 5, float(uv[10, p, 1]))}}
    with caplog.at_level(logging.WARNING):
        checked = track_video(_frames(small_video), labels, TrackOptions(), name="cam0")["m"]
    assert not any(f in checked for f in range(1, 10))
    # said, with the frames and how far apart the two sides were (a drag correction dropped 59 frames silently)
    said = [r.getMessage() for r in caplog.records if "point 'm': tracked frames 1-9 dropped" in r.getMessage()]
    assert len(said) == 1 and "cam0" in said[0] and re.search(r"median [3-6] px apart", said[0]), said
    assert 11 in checked  # after the last label nothing can be checked: tracked as usual
    unchecked = track_video(_frames(small_video), labels, TrackOptions(closure_check=False))["m"]
    assert all(f in unchecked for f in range(1, 10))


def test_invalid_options_fail_at_construction() -> None:
    for bad in ({"min_score": 1.5}, {"fb_threshold": 0.0}, {"win_size": 3}, {"patch": 1}):
        with pytest.raises(ValueError):
            TrackOptions(**bad)  # type: ignore[arg-type]
