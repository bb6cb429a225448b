"""Keyframes chosen by content (`sfm.keyframes`), bounded cross-video pairs (`sfm.pairs`), and an interrupted
`register` that resumes from the steps it had finished (`sfm.resume`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

import sfm.stage
from sfm import pairs
from sfm.frames import select_frames
from sfm.keyframes import MIN_KEYFRAMES, KeyframeReason, _bounded, _reason, _Reference, choose_keyframes
from sfm.options import CameraMotion, KeyframeSelection, Localize, RegisterOptions
from sfm.synthetic.room import noise_texture
from sfm.video import probe_video

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data_samples" / "video_sample"
WIDTH, HEIGHT = 160, 96
SLOW, FAST, CUT = 40, 30, 10  # frames panning 1 px per frame, then 6 px per frame, then another scene


def _panning_video(path: Path) -> Path:
    """A camera panning slowly, then fast, over a textured wall; then a cut to another wall."""
    rng = np.random.default_rng(5)
    wall, other = noise_texture((HEIGHT, 480), rng), noise_texture((HEIGHT, WIDTH), rng)
    shifts = np.concatenate([np.arange(SLOW), SLOW + 6 * np.arange(FAST)])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (WIDTH, HEIGHT))
    for x in shifts:
        writer.write(np.ascontiguousarray(wall[:, x : x + WIDTH]))
    for _ in range(CUT):
        writer.write(other)
    writer.release()
    return path


def test_keyframes_follow_the_motion(tmp_path: Path) -> None:
    """Few keyframes while the view moves slowly, many while it moves fast, one at a cut; a cap thins them."""
    info = probe_video(_panning_video(tmp_path / "pan.avi"))
    choice = choose_keyframes(info, motion=0.05, survival=0.6, max_frames=0)
    frames = choice.frames
    assert frames[0] == 0 and frames[-1] == info.num_frames - 1 and len(frames) >= MIN_KEYFRAMES
    slow = np.sum(frames < SLOW)
    fast = np.sum((frames >= SLOW) & (frames < SLOW + FAST))
    assert 2 <= slow <= 8 and fast >= 2 * slow  # 8 px (5 % of 160) per keyframe: every ~8 slow, ~2 fast frames
    assert SLOW + FAST in frames  # the cut
    reasons = dict(zip(frames.tolist(), choice.reasons, strict=True))
    assert reasons[0] is KeyframeReason.FIRST and reasons[SLOW + FAST] in {
        KeyframeReason.MOTION,
        KeyframeReason.OVERLAP,
    }
    entry = choice.to_json()
    assert entry["method"] == "content" and entry["count"] == len(frames) and not entry["thinned_to_max_frames"]
    assert sum(entry["by_reason"].values()) == len(frames)

    capped = choose_keyframes(info, motion=0.05, survival=0.6, max_frames=MIN_KEYFRAMES)
    assert len(capped.frames) == MIN_KEYFRAMES and capped.thinned and set(capped.frames) <= set(frames)


def test_the_masked_subject_does_not_start_keyframes(tmp_path: Path) -> None:
    """A still camera on a wall, a large textured subject sweeping across it: its motion and what it covers start
    keyframes by content, unless its masks are given."""
    rng = np.random.default_rng(7)
    wall, subject = noise_texture((HEIGHT, WIDTH), rng), noise_texture((HEIGHT - 16, 60), rng)
    count, step = 40, 2
    path = tmp_path / "subject.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (WIDTH, HEIGHT))
    masks = {}
    for frame in range(count):
        image, x = wall.copy(), step * frame - 20
        left, right = max(x, 0), min(x + 60, WIDTH)
        mask = np.full((HEIGHT, WIDTH), 255, np.uint8)
        if right > left:
            image[8 : HEIGHT - 8, left:right] = subject[:, left - x : right - x]
            mask[4 : HEIGHT - 4, max(left - 4, 0) : right + 4] = 0
        masks[frame] = mask
        writer.write(image)
    writer.release()
    info = probe_video(path)
    unmasked = choose_keyframes(info, motion=0.05, survival=0.6, max_frames=0)
    masked = choose_keyframes(info, motion=0.05, survival=0.6, max_frames=0, masks=masks.get)
    assert unmasked.candidates > 2  # the subject's motion or its occlusions
    assert masked.candidates == 2  # first and last: the background never moved


def test_lost_tracks_start_a_keyframe() -> None:
    corners = np.random.default_rng(0).uniform(0, 100, (40, 2))
    reference = _Reference(frame=0, start=corners, now=corners + 1.0, alive=np.ones(40, bool))
    assert _reason(reference, threshold=5.0, survival=0.6) is None
    reference.alive[:20] = False
    assert _reason(reference, threshold=5.0, survival=0.6) is KeyframeReason.OVERLAP
    reference.alive[:] = True
    reference.now = corners + 6.0
    assert _reason(reference, threshold=5.0, survival=0.6) is KeyframeReason.MOTION


def test_short_or_still_videos_send_evenly_spaced_frames() -> None:
    """Fewer than MIN_KEYFRAMES by content: the evenly spaced frames of `--keyframes-by even` (today's)."""

    class Info:
        num_frames = 57
        times = np.arange(57) / 30.0

    for count, cap in ((57, 12), (14, 4), (10, 6), (6, 6)):
        Info.num_frames, Info.times = count, np.arange(count) / 30.0
        choice = _bounded({0: KeyframeReason.FIRST, count - 1: KeyframeReason.LAST}, count, cap, {})
        assert choice.frames.tolist() == select_frames(Info, max_frames=cap).tolist()  # type: ignore[arg-type]
        assert set(choice.reasons) == {KeyframeReason.FILL}


def test_retrieval_pairs_link_similar_frames_and_grow_linearly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pairs, "WORDS", 64)
    rng = np.random.default_rng(1)
    places = rng.integers(0, 256, (12, 60, 128))  # what each part of the scene looks like to SIFT

    def seen(place: int) -> np.ndarray:
        return np.clip(places[place] + rng.normal(0, 6, places[place].shape), 0, 255).astype(np.uint8)

    names = {"a": [f"a/{i}" for i in range(12)], "b": [f"b/{i}" for i in range(12)]}
    words = pairs.word_vectors({f"{v}/{i}": seen(i) for v in names for i in range(12)})
    found = pairs.retrieval_pairs(names, words, 1)
    assert {(f"a/{i}", f"b/{i}") for i in range(12)} <= found

    def count(per_video: int) -> int:
        many = {v: [f"{v}/{i}" for i in range(per_video)] for v in "abc"}
        vectors = {n: words[f"a/{i % 12}"] for v in many for i, n in enumerate(many[v])}
        return len(pairs.build_pairs(many, overlap=5, keyframes=10, partners=3, words=vectors))

    for per_video in (40, 80):  # 3 videos: sequential + 3 partners in each of 2 others per image, 3 x 10 x 10
        assert count(per_video) <= 3 * per_video * (5 + 3 * 2) + 3 * 10 * 10


def _options() -> RegisterOptions:
    # Small and single-threaded: COLMAP is deterministic with one thread and a fixed seed.
    return RegisterOptions(
        camera_motion=CameraMotion.MOVING,
        keyframes_by=KeyframeSelection.EVEN,
        max_frames=4,
        long_side=240,
        max_features=500,
        localize=Localize.NONE,
        cross_partners=1,
        num_threads=1,
    )


def _steps(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Records the pycolmap stages that `register` runs."""
    ran: list[str] = []
    real = sfm.stage.run_isolated

    def recording(stage: str, *args: Any, **kwargs: Any) -> Any:
        ran.append(stage)
        return real(stage, *args, **kwargs)

    monkeypatch.setattr(sfm.stage, "run_isolated", recording)
    return ran


def _poses(ws: Path) -> dict[str, list[list[float]]]:
    cameras = json.loads((ws / "cameras.json").read_text())
    return {
        v["name"]: [np.ravel(f["R"]).tolist() + np.ravel(f["t"]).tolist() for f in v["frames"]]
        for v in cameras["videos"]
    }


def test_interrupted_register_resumes_after_extraction(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    videos = [SAMPLE / "cam0.mp4", SAMPLE / "cam1.mp4"]
    ran = _steps(monkeypatch)
    sfm.stage.run(videos, tmp_path / "straight", _options())
    assert ran == ["feature extraction", "matching", "mapping (incremental)"]

    def interrupt(*args: Any) -> Any:
        raise KeyboardInterrupt

    ws = tmp_path / "ws"
    with monkeypatch.context() as patch:
        patch.setattr(sfm.stage, "_match", interrupt)
        with pytest.raises(KeyboardInterrupt):
            sfm.stage.run(videos, ws, _options())
    ran.clear()
    sfm.stage.run(videos, ws, _options())
    assert ran == ["matching", "mapping (incremental)"]  # the features of the interrupted run were kept
    report = json.loads((ws / "register_report.json").read_text())
    assert report["reused_steps"] == ["extract"] and report["ok"]
    np.testing.assert_allclose(
        np.concatenate([np.ravel(p) for p in _poses(ws).values()]),
        np.concatenate([np.ravel(p) for p in _poses(tmp_path / "straight").values()]),
        atol=1e-9,
    )

    ran.clear()
    sfm.stage.run(videos, ws, _options())
    assert ran == [] and json.loads((ws / "register_report.json").read_text())["reused_steps"] == [
        "extract",
        "match",
        "map",
    ]
