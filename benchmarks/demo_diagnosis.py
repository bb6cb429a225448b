"""Where the video demo loses accuracy: registration, 2D tracks, solver, measured stage by stage on the sample.

Needs a finished `dynrecon run` workspace of the sample (WS with register/cameras.json and tracks.csv):

    nice -n 10 python benchmarks/demo_diagnosis.py --ws WS [--sample data_samples/video_sample] [--solve]

Prints markdown tables:
- registration: per video, camera centre error (mm) and rotation error (deg) after the similarity that maps the
  registered cameras onto the true ones (`dynrecon.pipeline.similarity_to_truth`), and the pixel distance between
  the true joints projected by the aligned registered camera and by the true camera (what the solver sees);
- tracks: per video, observations kept / joints visible, and the pixel error of labels and tracked positions
  against the true projections;
- solver (`--solve`, minutes each): the same solver on true cameras + true 2D (at the tracked rows), true cameras +
  tracked 2D, registered cameras + true 2D, registered + tracked (the pipeline), and true cameras + true 2D at every
  visible joint (the observation pattern's cost).

`--screenshot PNG` instead renders WS/recording.rrd to a picture (the README's): rerun's web viewer
(`rerun --serve-web`) opened in headless chromium (`/usr/bin/chromium`, software WebGL), side panels collapsed,
quantized to 256 colours.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
import urllib.parse
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.demo import pipeline_options
from dynrecon.pipeline import REGISTER_DIR
from dynrecon.truth import similarity_to_truth, truth_of_frames
from reconstruct.outputs.points import FramePoints, read_points
from reconstruct.stage import run as solve_run
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras, write_cameras
from simulation.evaluate import ReconstructionAccuracy, evaluate
from tracking.tracks import Tracks, read_tracks, write_tracks

log = logging.getLogger(__name__)

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "video_sample"


def project(camera: FrameCamera, xyz: np.ndarray) -> np.ndarray:
    """xyz: (P, 3) world -> (P, 2) pixels (no distortion: the sample's cameras have none)."""
    x = (xyz @ camera.R.T + camera.t) @ camera.K.T
    return x[:, :2] / x[:, 2:]


def frames_of(cameras: CameraSet) -> dict[tuple[str, int], FrameCamera]:
    return {(v.name, f.frame): f for v in cameras.videos for f in v.frames}


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def registration_table(cameras: CameraSet, truth_cameras: CameraSet, truth: FramePoints) -> str:
    sim = similarity_to_truth(cameras, truth_cameras)
    true = frames_of(truth_cameras)
    index = truth.index()
    rows = [
        "| video | frames registered | centre err mean / max (mm) | rotation err mean / max (deg) | "
        "reprojection of true joints mean / max (px) |",
        "|---|---|---|---|---|",
    ]
    everything: list[np.ndarray] = []
    for video in cameras.videos:
        centre, rotation, pixels = [], [], []
        for frame in video.frames:
            truth_camera = true[(video.name, frame.frame)]
            aligned = sim.camera(frame)
            centre.append(np.linalg.norm(aligned.center - truth_camera.center))
            rotation.append(rotation_deg(aligned.R, truth_camera.R))
            xyz = truth.xyz[index[(video.name, frame.frame)]]
            pixels.append(np.linalg.norm(project(aligned, xyz) - project(truth_camera, xyz), axis=1))
        px = np.concatenate(pixels)
        everything.append(px)
        rows.append(
            f"| {video.name} | {len(video.frames)}/{len(truth_cameras.video(video.name).frames)} | "
            f"{np.mean(centre):.1f} / {np.max(centre):.1f} | {np.mean(rotation):.3f} / "
            f"{np.max(rotation):.3f} | {px.mean():.2f} / {px.max():.2f} |"
        )
    rows.append(
        f"\nscale {sim.scale:.2f} mm per SfM unit; all videos: true joints reproject "
        f"{np.concatenate(everything).mean():.2f} px mean from where the registered cameras put them"
    )
    return "\n".join(rows)


def true_tracks(tracks: Tracks, truth_cameras: CameraSet, truth: FramePoints) -> Tracks:
    """`tracks` with every position replaced by the true projection of its joint (same rows)."""
    true = frames_of(truth_cameras)
    index = truth.index()
    points = {name: i for i, name in enumerate(truth.point_names)}
    xy = np.array(
        [
            project(true[(v, int(f))], truth.xyz[index[(v, int(f))]][[points[p]]])[0]
            for v, f, p in zip(tracks.video, tracks.frame, tracks.point, strict=True)
        ]
    ).reshape(-1, 2)
    return dataclasses.replace(tracks, xy=xy, line=None, path=None)


def visible_tracks(truth_cameras: CameraSet, truth: FramePoints) -> Tracks:
    """True projections of every joint in every frame where it lies inside the image: an upper bound on what a
    tracker could observe (occlusion is ignored, so slightly generous)."""
    index = truth.index()
    rows: list[tuple[str, int, str, float, float]] = []
    for video in truth_cameras.videos:
        for camera in video.frames:
            uv = project(camera, truth.xyz[index[(video.name, camera.frame)]])
            for name, (u, v) in zip(truth.point_names, uv, strict=True):
                if 0 <= u < video.width and 0 <= v < video.height:
                    rows.append((video.name, camera.frame, name, float(u), float(v)))
    return Tracks.from_rows(rows, source=["label"] * len(rows), score=["1.000"] * len(rows))


def tracks_table(tracks: Tracks, truth_cameras: CameraSet, truth: FramePoints) -> str:
    exact = true_tracks(tracks, truth_cameras, truth).xy
    error = np.linalg.norm(tracks.xy - exact, axis=1)
    source = np.array(tracks.extra.get("source", ["tracked"] * len(tracks)))
    visible = visible_tracks(truth_cameras, truth)
    rows = [
        "| video | frames | joints in view | labels (err mean px) | tracked kept (err mean / p95 / max px) | "
        "tracked > 3 px |",
        "|---|---|---|---|---|---|",
    ]
    for video in truth_cameras.videos:
        mine = np.array([v == video.name for v in tracks.video])
        lab, trk = mine & (source == "label"), mine & (source != "label")
        in_view = sum(v == video.name for v in visible.video)
        e = error[trk]
        rows.append(
            f"| {video.name} | {len(video.frames)} | {in_view} | {lab.sum()} ({error[lab].mean():.2f}) | "
            f"{trk.sum()} ({e.mean():.2f} / {np.percentile(e, 95):.2f} / {e.max():.1f}) | "
            f"{(e > 3).sum()} |"
        )
    return "\n".join(rows)


def solve_and_score(
    cameras: CameraSet, tracks: Tracks, truth_cameras: CameraSet, truth: FramePoints, work: Path
) -> tuple[ReconstructionAccuracy, float]:
    work.mkdir(parents=True, exist_ok=True)
    write_cameras(work / "cameras.json", cameras)
    write_tracks(work / "tracks.csv", tracks)
    started = time.perf_counter()
    # The demo's solve options (its clock settings matter on the periodic sample: see dynrecon.demo).
    options = dataclasses.replace(pipeline_options(SAMPLE).solve, recording=None)
    solve_run(work / "cameras.json", work / "tracks.csv", work, options)
    seconds = time.perf_counter() - started
    points = read_points(work / "points3d.csv")
    sim = similarity_to_truth(cameras, truth_cameras)
    aligned = dataclasses.replace(points, xyz=sim.apply(points.xyz))
    return evaluate(aligned, truth_of_frames(truth, aligned)), seconds


def screenshot(
    recording: Path,
    png: Path,
    *,
    wait_s: float = 45.0,
    web_port: int = 9191,
    grpc_port: int = 9877,
    zoom_steps: int = 1,
    zoom_at: tuple[int, int] = (420, 460),
) -> Path:
    """A 1280 x 720 picture of `recording` in rerun's web viewer (headless chromium, swiftshader WebGL)."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    # Own session: `rerun` is a launcher that starts the viewer binary as a child; ending the launcher alone left the
    # server running on the ports (and the next screenshot showed the old recording).
    server = subprocess.Popen(
        ["rerun", "--serve-web", "--web-viewer-port", str(web_port), "--port", str(grpc_port), str(recording)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        time.sleep(5)  # the server loads the file before the page asks for it
        source = urllib.parse.quote(f"rerun+http://localhost:{grpc_port}/proxy", safe="")
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path="/usr/bin/chromium",
                headless=True,
                args=[
                    "--use-gl=angle",
                    "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader",
                    "--ignore-gpu-blocklist",
                ],
            )
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.goto(f"http://localhost:{web_port}/?url={source}&renderer=webgl")
            time.sleep(wait_s)  # software rendering: the first frames take tens of seconds
            for x in (1256, 1229, 1201):  # the right, bottom and left panel toggles (top right corner)
                page.mouse.click(x, 18)
                time.sleep(3)
            for _ in range(zoom_steps):  # closer to the subject in the 3D view (top left)
                page.mouse.move(*zoom_at)
                page.mouse.wheel(0, -120)
                time.sleep(1)
            page.mouse.move(1279, 719)  # no hover highlight on the views
            time.sleep(8)
            raw = png.with_suffix(".raw.png")
            page.screenshot(path=str(raw))
            browser.close()
    finally:
        os.killpg(server.pid, signal.SIGTERM)  # the launcher and the viewer it started
        server.wait(timeout=30)
    png.parent.mkdir(parents=True, exist_ok=True)
    Image.open(raw).convert("RGB").quantize(colors=256).save(png, optimize=True)
    raw.unlink()
    return png


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ws", type=Path, required=True)
    parser.add_argument("--sample", type=Path, default=SAMPLE)
    parser.add_argument("--solve", action="store_true", help="run the solver experiments (minutes each)")
    parser.add_argument("--only", default="", help="comma-separated experiment numbers to run (default all)")
    parser.add_argument("--screenshot", type=Path, metavar="PNG", help="render WS/recording.rrd to PNG and stop")
    args = parser.parse_args()
    if args.screenshot is not None:
        print(screenshot(args.ws / "recording.rrd", args.screenshot))
        return
    logging.basicConfig(level=logging.WARNING, format="%(levelname).1s %(name)s: %(message)s")
    cameras = read_cameras(args.ws / REGISTER_DIR / "cameras.json")
    truth_cameras = read_cameras(args.sample / "truth_cameras.json")
    truth = read_points(args.sample / "truth.csv")
    tracks = read_tracks(args.ws / "tracks.csv")
    print("## Registration\n")
    print(registration_table(cameras, truth_cameras, truth), "\n")
    print("## 2D tracks\n")
    print(tracks_table(tracks, truth_cameras, truth), "\n")
    if not args.solve:
        return
    registered = frames_of(cameras)
    true_set = CameraSet(
        videos=[
            VideoCameras(
                name=v.name,
                width=v.width,
                height=v.height,
                fps=v.fps,
                frames=[f for f in v.frames if (v.name, f.frame) in registered],
            )
            for v in truth_cameras.videos
        ]
    )
    exact = true_tracks(tracks, truth_cameras, truth)
    experiments = [
        ("true cameras + true 2D (tracked rows)", true_set, exact),
        ("true cameras + tracked 2D", true_set, tracks),
        ("registered cameras + true 2D (tracked rows)", cameras, exact),
        ("registered cameras + tracked 2D (pipeline)", cameras, tracks),
        ("true cameras + true 2D, every joint in view", true_set, visible_tracks(true_set, truth)),
    ]
    wanted = {int(x) for x in args.only.split(",") if x}
    print("## Solver\n")
    print("| # | cameras + 2D | observations | <10 mm | <20 mm | <50 mm | median mm | solve s |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    with tempfile.TemporaryDirectory() as scratch:
        for number, (name, cams, trk) in enumerate(experiments, start=1):
            if wanted and number not in wanted:
                continue
            accuracy, seconds = solve_and_score(cams, trk, truth_cameras, truth, Path(scratch) / str(number))
            share = dict(zip(accuracy.thresholds, accuracy.share_under, strict=True))
            print(
                f"| {number} | {name} | {len(trk)} | {100 * share[10.0]:.1f} % | "
                f"{100 * share[20.0]:.1f} % | {100 * share[50.0]:.1f} % | {accuracy.median:.1f} | "
                f"{seconds:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
