"""Drive the real labeling page in headless Chromium: label, track, correct, undo, reload, check the files.

Needs Debian's chromium (`apt-get install -y chromium`) and Playwright's Python package; skipped otherwise.
The screenshot is written to tmp_path/labeling.png (path printed); with DYNRECON_UPDATE_DOCS_IMAGES=1 it is also
copied to docs/images/labeling.png for the README.
"""

from __future__ import annotations

import csv
import errno
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynrecon import atomic
from labeling.skeleton import Skeleton
from labeling.stage import LabelOptions, LabelServer
from tracking.labels import Source, read_labels

CHROMIUM = Path("/usr/bin/chromium")
REPO = Path(__file__).resolve().parents[2]
WIDTH, HEIGHT, FRAMES = 640, 360, 30
POINTS = ("head", "hand", "foot")
RADIUS = 18

pytestmark = pytest.mark.browser


def truth(point: str, frame: int) -> tuple[float, float]:
    """Ground-truth centres of three textured discs: a chain swinging across a textured background."""
    t = frame / (FRAMES - 1)
    base_x, base_y = 230.0 + 120.0 * t, 110.0 + 20.0 * np.sin(2 * np.pi * t)
    if point == "head":
        return base_x, base_y
    angle = 0.6 * np.sin(2 * np.pi * t)
    if point == "hand":
        return base_x + 90.0 * np.cos(angle), base_y + 90.0 * np.sin(angle) + 20.0
    return base_x - 30.0 + 20.0 * t, base_y + 150.0


def write_scene(path: Path) -> Path:
    rng = np.random.default_rng(7)
    # A soft, floor-like texture: coarse blotches plus a little fine grain.
    coarse = cv2.resize(
        rng.integers(0, 256, size=(HEIGHT // 24, WIDTH // 24), dtype=np.uint8),
        (WIDTH, HEIGHT),
        interpolation=cv2.INTER_CUBIC,
    ).astype(np.float32)[..., None]
    grain = rng.normal(0.0, 12.0, size=(HEIGHT, WIDTH, 1)).astype(np.float32)
    background = np.clip(0.45 * coarse + np.float32([55, 62, 70]) + grain, 0, 255).astype(np.uint8)
    size = 2 * RADIUS + 1
    yy, xx = np.mgrid[:size, :size]
    inside = (xx - RADIUS) ** 2 + (yy - RADIUS) ** 2 <= RADIUS**2
    # Random blobs of texture (no periodic pattern: LK would lock onto the wrong period).
    blotches = {p: cv2.resize(rng.random((size // 3, size // 3)).astype(np.float32), (size, size)) for p in POINTS}
    # Muted colours, so the page's markers stand out in the screenshot.
    tints = {"head": (190, 200, 215), "hand": (215, 195, 175), "foot": (185, 215, 190)}
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 15.0, (WIDTH, HEIGHT))
    for frame in range(FRAMES):
        image = background.copy()
        for point in POINTS:
            texture = (blotches[point][..., None] * np.array(tints[point], np.float32)).astype(np.uint8)
            # Sub-pixel centres: render at 4x and shift, so ground truth is not limited to integer pixels.
            cx, cy = truth(point, frame)
            x0, y0 = int(np.floor(cx)) - RADIUS, int(np.floor(cy)) - RADIUS
            shift = np.float32([[1, 0, cx - np.floor(cx)], [0, 1, cy - np.floor(cy)]])
            moved = cv2.warpAffine(
                texture, shift, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
            mask = cv2.warpAffine(inside.astype(np.uint8), shift, (size, size)).astype(bool)
            region = image[y0 : y0 + size, x0 : x0 + size]
            region[mask] = moved[mask]
        writer.write(image)
    writer.release()
    return path


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture
def browser():
    if not CHROMIUM.exists():
        pytest.skip("needs Debian's chromium at /usr/bin/chromium (apt-get install -y chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="needs Playwright's Python package")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM),
            args=[
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
            ],
        )
        try:
            yield browser
        finally:
            browser.close()


def click_image(page, u: float, v: float) -> None:
    x, y = page.evaluate("([u, v]) => window.dynreconLabel.toClient(u, v)", [u, v])
    page.mouse.click(x, y)


def drag_image(page, start: tuple[float, float], end: tuple[float, float]) -> None:
    x0, y0 = page.evaluate("([u, v]) => window.dynreconLabel.toClient(u, v)", list(start))
    x1, y1 = page.evaluate("([u, v]) => window.dynreconLabel.toClient(u, v)", list(end))
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move((x0 + x1) / 2, (y0 + y1) / 2, steps=3)
    page.mouse.move(x1, y1, steps=3)
    page.mouse.up()


def goto_frame(page, frame: int) -> None:
    page.fill("#frame", str(frame))
    page.press("#frame", "Enter")
    page.wait_for_function(
        # imgKey stays null until the first image has loaded: a throwing predicate would end the wait.
        "f => window.dynreconLabel.state.frame === f && (window.dynreconLabel.state.imgKey ?? '').endsWith('|' + f)",
        arg=frame,
    )


def wait_saved(page) -> None:
    page.wait_for_function("document.getElementById('save-status').dataset.pending === '0'")
    assert page.inner_text("#save-status") == "saved"


def run_tracking(page, runs_before: int) -> None:
    page.click("#track")
    page.wait_for_function(
        "n => document.body.dataset.trackState !== 'running' && Number(document.body.dataset.trackSeq) > n",
        arg=runs_before,
        timeout=120_000,
    )
    assert page.evaluate("document.body.dataset.trackState") == "done", page.inner_text("#track-status")


def show(capsys: pytest.CaptureFixture[str], text: str) -> None:
    """A line in the test output even when pytest captures stdout (the screenshot's path, the numbers)."""
    with capsys.disabled():
        print(f"\n{text}")


def test_label_track_correct_undo_reload(browser, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    video = write_scene(tmp_path / "swing.avi")
    workspace = tmp_path / "swing-workspace"
    skeleton = Skeleton(points=list(POINTS), connections=[("head", "hand"), ("head", "foot")])
    with LabelServer(workspace, LabelOptions(videos=[video], skeleton=skeleton)) as server:
        page = browser.new_page(viewport={"width": 1280, "height": 760})
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(server.url)
        page.wait_for_selector("body[data-ready='1']")

        # Frame 0: click all three points (the selection advances after each click).
        goto_frame(page, 0)
        # Mouse events carry whole CSS pixels: a click lands within one screen pixel of the target.
        tolerance = {0: 1.5 / page.evaluate("window.dynreconLabel.state.view.scale")}
        page.click("li[data-point='head']")
        for point in POINTS:
            click_image(page, *truth(point, 0))
        # Frame 20, zoomed in around the head first (wheel), so the clicks go through the zoomed view.
        goto_frame(page, 20)
        hx, hy = page.evaluate("([u, v]) => window.dynreconLabel.toClient(u, v)", list(truth("head", 20)))
        page.mouse.move(hx, hy)
        page.mouse.wheel(0, -400)
        page.wait_for_function("window.dynreconLabel.state.view.scale > 2.5")
        tolerance[20] = 1.5 / page.evaluate("window.dynreconLabel.state.view.scale")
        page.click("li[data-point='head']")
        for point in POINTS:
            click_image(page, *truth(point, 20))
        # The foot leaves the picture on frame 25 (say): "not visible here" with the X key.
        page.click("li[data-point='foot']")
        goto_frame(page, 25)
        page.focus("#canvas")
        page.keyboard.press("x")
        wait_saved(page)
        page.keyboard.press("f")

        labels = read_labels(workspace / "labels.csv")
        assert labels[("swing", 25, "foot")].source is Source.HIDDEN
        for frame in (0, 20):
            for point in POINTS:
                xy = labels[("swing", frame, point)].xy
                assert xy is not None
                error = np.hypot(xy[0] - truth(point, frame)[0], xy[1] - truth(point, frame)[1])
                assert error < tolerance[frame], (point, frame, error)

        # Track: positions between the labels appear in the page, in another style, with a score.
        run_tracking(page, 0)
        tracks = read_rows(workspace / "tracks.csv")
        tracked = [r for r in tracks if r["source"] == "track"]
        assert {int(r["frame"]) for r in tracked if r["point"] == "head"} >= set(range(1, 20))
        errors_px = [
            np.hypot(
                float(r["x"]) - truth(r["point"], int(r["frame"]))[0],
                float(r["y"]) - truth(r["point"], int(r["frame"]))[1],
            )
            for r in tracked
        ]
        show(
            capsys,
            f"tracked positions: {len(tracked)}, median error {np.median(errors_px):.2f} px, "
            f"max {np.max(errors_px):.2f} px",
        )
        assert np.median(errors_px) < 1.0
        assert not [r for r in tracks if r["point"] == "foot" and int(r["frame"]) == 25]
        goto_frame(page, 10)
        state = page.evaluate("window.dynreconLabel.state.tracks.get('10|hand')")
        assert state is not None and 0 < state["score"] <= 1
        assert "track" in page.inner_text("li[data-point='hand'] .state")

        # Correct frame 10: drag the tracked hand 3 px right; the correction is a label that re-anchors.
        page.click("li[data-point='hand']")
        hand = (state["x"], state["y"])
        corrected = (round(truth("hand", 10)[0] + 3.0, 1), round(truth("hand", 10)[1], 1))
        drag_image(page, hand, corrected)
        # A second correction on frame 12, which is then undone.
        goto_frame(page, 12)
        page.click("li[data-point='head']")
        # Far enough from the tracked marker not to grab it (a click on a marker only selects).
        click_image(page, truth("head", 12)[0] + 12.0, truth("head", 12)[1])
        page.wait_for_function("window.dynreconLabel.state.labels.has('12|head')")
        wait_saved(page)
        assert ("swing", 12, "head") in read_labels(workspace / "labels.csv")
        page.keyboard.press("Control+z")
        page.wait_for_function("!window.dynreconLabel.state.labels.has('12|head')")
        wait_saved(page)
        labels = read_labels(workspace / "labels.csv")
        assert ("swing", 12, "head") not in labels
        hand_label = labels[("swing", 10, "hand")].xy
        assert hand_label is not None
        assert np.hypot(hand_label[0] - corrected[0], hand_label[1] - corrected[1]) < tolerance[0]

        run_tracking(page, 1)
        tracks = read_rows(workspace / "tracks.csv")
        by_key = {(int(r["frame"]), r["point"]): r for r in tracks}
        assert by_key[(10, "hand")]["source"] == "label"
        assert abs(float(by_key[(10, "hand")]["x"]) - corrected[0]) < tolerance[0]
        assert by_key[(12, "head")]["source"] == "track"
        # Re-anchored: the next frame follows the correction (3 px right of the truth), not the old track.
        assert float(by_key[(11, "hand")]["x"]) - truth("hand", 11)[0] > 1.5

        # Reload: labels and tracks come back from the files, the place from the URL.
        page.evaluate("location.hash = '#video=swing&frame=10&point=hand'")
        page.reload()
        page.wait_for_selector("body[data-ready='1']")
        page.wait_for_function("window.dynreconLabel.state.imgKey === 'swing|10'")
        state = page.evaluate("""() => { const s = window.dynreconLabel.state;
            return {labels: s.labels.size, tracks: s.tracks.size, frame: s.frame, selected: s.selected}; }""")
        assert state == {
            "labels": 8,
            "tracks": sum(1 for r in tracks if r["source"] == "track"),
            "frame": 10,
            "selected": "hand",
        }
        goto_frame(page, 10)
        middle = np.mean([truth(p, 10) for p in POINTS], axis=0)
        x, y = page.evaluate("([u, v]) => window.dynreconLabel.toClient(u, v)", [float(m) for m in middle])
        page.mouse.move(x, y)
        page.mouse.wheel(0, -300)  # zoom in a little for the picture
        page.wait_for_function("window.dynreconLabel.state.view.scale > 2")
        page.mouse.move(5, 5)  # no hover effects in the picture
        shot = tmp_path / "labeling.png"
        page.screenshot(path=str(shot))
        show(capsys, f"labeling page screenshot: {shot}")
        assert not errors, errors
    if os.environ.get("DYNRECON_UPDATE_DOCS_IMAGES") == "1":  # tests never write into the checkout by default
        images = REPO / "docs" / "images"
        images.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, images / "labeling.png")


def test_points_keys_and_auto_track(browser, tmp_path: Path) -> None:
    """Add and rename a point, navigate with keys, and let a change start tracking by itself."""
    video = write_scene(tmp_path / "swing.avi")
    workspace = tmp_path / "ws"
    with LabelServer(workspace, LabelOptions(videos=[video], skeleton=Skeleton(points=["head"]))) as server:
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(server.url)
        page.wait_for_selector("body[data-ready='1']")

        page.fill("#new-point", "toe")
        page.press("#new-point", "Enter")
        page.wait_for_selector("li[data-point='toe'].active")
        page.dblclick("li[data-point='toe'] .name")
        page.fill("li[data-point='toe'] input.rename-input", "heel")
        page.press("li[data-point='toe'] input.rename-input", "Enter")
        page.wait_for_selector("li[data-point='heel']")
        assert json.loads((workspace / "labeling.json").read_text())["points"] == ["head", "heel"]

        page.check("#auto-track")
        page.click("li[data-point='heel']")
        click_image(page, *truth("foot", 0))
        page.focus("#canvas")
        for _ in range(3):
            page.keyboard.press("Shift+ArrowRight")  # 10 frames each
        page.wait_for_function("window.dynreconLabel.state.frame === 29")
        page.click("li[data-point='heel']")
        click_image(page, *truth("foot", 29))
        page.wait_for_function(
            "Number(document.body.dataset.trackSeq) >= 1 && document.body.dataset.trackState === 'done'",
            timeout=120_000,
        )
        tracks = read_rows(workspace / "tracks.csv")
        page.wait_for_function("window.dynreconLabel.state.tracks.size > 0")
        assert {r["point"] for r in tracks} == {"heel"}
        assert {int(r["frame"]) for r in tracks if r["source"] == "label"} == {0, 29}
        assert {int(r["frame"]) for r in tracks if r["source"] == "track"} == set(range(1, 29))

        # Enter keeps a tracked position as a label; Delete removes a label again.
        tracked_5 = next(r for r in tracks if r["frame"] == "5")
        goto_frame(page, 5)
        page.click("li[data-point='heel']")
        page.focus("#canvas")
        page.keyboard.press("Enter")
        page.wait_for_function("window.dynreconLabel.state.labels.has('5|heel')")
        wait_saved(page)
        kept = read_labels(workspace / "labels.csv")[("swing", 5, "heel")].xy
        assert kept is not None
        assert np.hypot(kept[0] - float(tracked_5["x"]), kept[1] - float(tracked_5["y"])) < 0.01
        page.keyboard.press("Delete")
        page.wait_for_function("!window.dynreconLabel.state.labels.has('5|heel')")
        wait_saved(page)
        assert ("swing", 5, "heel") not in read_labels(workspace / "labels.csv")

        # Shift+drag pans the view and places nothing.
        before = page.evaluate("({...window.dynreconLabel.state.view})")
        labels_before = page.evaluate("window.dynreconLabel.state.labels.size")
        page.keyboard.down("Shift")
        drag_image(page, (300.0, 200.0), (250.0, 150.0))
        page.keyboard.up("Shift")
        after = page.evaluate("({...window.dynreconLabel.state.view})")
        assert after["tx"] < before["tx"] - 20 and after["ty"] < before["ty"] - 20
        assert page.evaluate("window.dynreconLabel.state.labels.size") == labels_before

        # N jumps to the next frame where the selected point has neither label nor track.
        page.keyboard.press("Home")
        page.click("li[data-point='head']")
        page.focus("#canvas")
        page.keyboard.press("n")
        page.wait_for_function("window.dynreconLabel.state.frame === 1")
        assert not errors, errors


def test_a_full_disk_is_shown_and_the_click_saved_later(
    browser, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The page shows the server's one-line reason (507) and keeps retrying until the disk has room again."""
    video = write_scene(tmp_path / "swing.avi")
    workspace = tmp_path / "ws"
    with LabelServer(workspace, LabelOptions(videos=[video], skeleton=Skeleton(points=["head"]))) as server:
        page = browser.new_page(viewport={"width": 1100, "height": 700})
        page.goto(server.url)
        page.wait_for_selector("body[data-ready='1']")

        def disk_full(fd: int) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(atomic.os, "fsync", disk_full)
        page.click("li[data-point='head']")
        click_image(page, *truth("head", 0))
        page.wait_for_function("document.getElementById('save-status').textContent.includes('No space left')")
        shown = page.inner_text("#save-status")
        assert shown.startswith("not saved: cannot save labels.csv: No space left on device"), shown
        assert not (workspace / "labels.csv").exists()
        assert not [p.name for p in workspace.iterdir() if p.name.endswith(".tmp")]
        monkeypatch.undo()
        wait_saved_within(page, 15_000)
        assert set(read_labels(workspace / "labels.csv")) == {("swing", 0, "head")}


def wait_saved_within(page, timeout_ms: int) -> None:
    page.wait_for_function("document.getElementById('save-status').dataset.pending === '0'", timeout=timeout_ms)
    assert page.inner_text("#save-status") == "saved"
