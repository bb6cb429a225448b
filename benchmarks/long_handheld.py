"""Acceptance (issue 19): a long handheld capture, every frame registered, and what each stage costs.

    python benchmarks/long_handheld.py [--seconds 30] [--fps 30] [--size 1920x1080] [--out /tmp/long_handheld]
        [--threads -1] [--check] [--max-frames N] [--no-added-keyframes]

Three handheld cameras walk along the near side of the synthetic room (sfm/synthetic: the same walls, textures and
camera model as the tests), swinging about 1 m along it and back, panning across the far wall, with a walking bob
and a hand's small shake. Videos are rendered once (cached in --out, mp4v) at --fps for --seconds; then
`sfm.register` runs with its defaults (content keyframes, in-between frames by tracking) and every frame is
compared with the truth after a similarity. Prints a table (stage, seconds, frames, frames/s) and the accuracy,
overall and per path (sfm, tracked, sift; frames without a pose).

A low `--max-frames` (a keyframe budget forced low) leaves long stretches between keyframes where the camera moves
away from all of them: there the in-between frames are posed by tracking from keyframes added on the way
(`sfm.track_pose`), or, with `--no-added-keyframes` (today's behaviour before them), fall to SIFT or stay unposed.

The walls are drawn by one homography per wall (a plane's texture seen by a pinhole camera), which is what
`sfm.synthetic.room.render` computes per pixel; `--check` compares the two on one small frame. No spheres: the
subject is not what this measures.
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm import RegisterOptions, track_pose
from sfm import register as run_register
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras, write_cameras
from sfm.evaluate import compare
from sfm.report import posed_frames
from sfm.synthetic.room import TEXELS_PER_METRE, Room, render
from sfm.synthetic.scene import look_at

ROOM_SEED = 0
SHAKE_DEG = 0.3  # amplitude of the hand's rotation shake
BOB_M = 0.02  # amplitude of the walking bob (vertical)
SWING_M = 1.0  # amplitude of the walk along the room
SWING_PERIOD_S = 30.0
PAD = 4  # texels of reflected border around each wall texture
STAGES = ("probe", "motion_test", "keyframes", "decode", "extract", "match", "map", "localize", "subject", "export")


@dataclass(kw_only=True)
class Handheld:
    """One handheld camera: a walk along x about `start`, looking at `target` swept across the far wall."""

    name: str
    K: np.ndarray  # (3, 3)
    start: np.ndarray  # (3,) centre at time 0
    target: np.ndarray  # (3,) looked-at point at time 0
    phase: float

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3), t (3,)) cam_from_world at `time` seconds."""
        swing = SWING_M * np.sin(2 * np.pi * time / SWING_PERIOD_S + self.phase) - SWING_M * np.sin(self.phase)
        centre = self.start + np.array(
            [swing, 0.2 * np.sin(2 * np.pi * time / 9.0 + self.phase), BOB_M * np.sin(2 * np.pi * 1.8 * time)]
        )
        target = self.target + np.array(
            [1.2 * np.sin(2 * np.pi * time / 17.0 + self.phase), 0.0, 0.25 * np.sin(2 * np.pi * time / 13.0)]
        )
        shake = np.radians(SHAKE_DEG) * np.array(
            [np.sin(2 * np.pi * 1.7 * time + k + self.phase) * np.cos(2 * np.pi * 0.9 * time + 2 * k) for k in range(3)]
        )
        R = cv2.Rodrigues(shake)[0] @ look_at(centre, target)
        return R, -R @ centre


def handheld_cameras(width: int, height: int) -> list[Handheld]:
    """Three cameras on the room's y = 0 side, 2.5-3 m apart, looking at the far wall (y = 6)."""
    setups = [(1.00, [1.6, 0.8, 1.5], [3.0, 6.0, 1.3]), (1.12, [4.0, 0.7, 1.7], [4.0, 6.0, 1.2]),
              (0.92, [6.4, 0.9, 1.3], [5.0, 6.0, 1.4])]  # fmt: skip
    cameras = []
    for index, (focal, start, target) in enumerate(setups):
        f = 0.78 * width * focal
        K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
        cameras.append(
            Handheld(name=f"cam{index}", K=K, start=np.array(start), target=np.array(target), phase=1.3 * index)
        )
    return cameras


def render_walls(room: Room, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 BGR view of the room's walls: each wall's texture warped by its homography."""
    origin = -R.T @ t
    M = R.T @ np.linalg.inv(K)  # world ray direction of pixel (u, v, 1)
    u = np.arange(width, dtype=np.float32)
    v = np.arange(height, dtype=np.float32)[:, None]
    directions = [np.float32(M[a, 0]) * u + np.float32(M[a, 1]) * v + np.float32(M[a, 2]) for a in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        # A ray leaves the box through the nearer of its two planes on each axis: the larger of the two ts.
        exits = [
            np.fmax(np.float32(room.size[a] - origin[a]) / d, np.float32(-origin[a]) / d)
            for a, d in enumerate(directions)
        ]
    axis_hit = np.where(exits[0] <= exits[1], 0, 1)
    axis_hit = np.where(np.minimum(exits[0], exits[1]) <= exits[2], axis_hit, 2)
    label = (2 * axis_hit + np.choose(axis_hit, [d > 0 for d in directions])).astype(np.uint8)
    image = np.zeros((height, width, 3), np.uint8)
    for wall in np.unique(label):
        axis, side = divmod(int(wall), 2)
        # Reflect-padded textures with a constant border: reflecting far-off coordinates is slow in OpenCV.
        texture = cv2.copyMakeBorder(room.textures[wall], PAD, PAD, PAD, PAD, cv2.BORDER_REFLECT)
        shift = np.array([[1.0, 0.0, PAD], [0.0, 1.0, PAD], [0.0, 0.0, 1.0]])
        warped = cv2.warpPerspective(
            texture,
            shift @ _wall_homography(M, origin, axis, float(room.size[axis]) * side),
            (width, height),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
        )
        np.copyto(image, warped, where=(label == wall)[..., None])
    return image


def _wall_homography(M: np.ndarray, origin: np.ndarray, axis: int, bound: float) -> np.ndarray:
    """(3, 3) pixel -> texel map of the wall at coordinate `bound` on `axis` (room.render's texel convention)."""
    u_axis, v_axis = [a for a in range(3) if a != axis]
    depth = bound - origin[axis]
    rows = [TEXELS_PER_METRE * (origin[j] * M[axis] + depth * M[j]) - 0.5 * M[axis] for j in (u_axis, v_axis)]
    return np.stack([*rows, M[axis]])


def check_renderer() -> float:
    """Largest mean absolute difference (grey levels) between render_walls and room.render on small frames."""
    room = Room(seed=ROOM_SEED)
    worst = 0.0
    for camera in handheld_cameras(320, 180):
        R, t = camera.pose(3.0)
        ours = render_walls(room, camera.K, R, t, 320, 180).astype(float)
        theirs = render(room, camera.K, R, t, 320, 180)[0].astype(float)
        worst = max(worst, float(np.abs(ours - theirs).mean()))
    return worst


def _render_frame(args: tuple[Handheld, float, int, int]) -> np.ndarray:
    camera, time, width, height = args
    R, t = camera.pose(time)
    return render_walls(_ROOM, camera.K, R, t, width, height)


_ROOM = Room(seed=ROOM_SEED)


def render_capture(out: Path, seconds: float, fps: float, width: int, height: int, workers: int) -> list[Path]:
    """The three videos (cached) and truth_cameras.json in `out`; returns the video paths."""
    cameras = handheld_cameras(width, height)
    truth_path = out / "truth_cameras.json"
    paths = [out / f"{c.name}.mp4" for c in cameras]
    if truth_path.exists() and all(p.exists() for p in paths):
        return paths
    out.mkdir(parents=True, exist_ok=True)
    times = np.arange(round(seconds * fps)) / fps
    truth = CameraSet()
    started = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        for camera, path in zip(cameras, paths, strict=True):
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, (width, height))
            jobs = [(camera, float(s), width, height) for s in times]
            for image in pool.map(_render_frame, jobs, chunksize=8):
                writer.write(image)
            writer.release()
            frames = []
            for index, s in enumerate(times):
                R, t = camera.pose(float(s))
                frames.append(FrameCamera(frame=index, time=float(s), K=camera.K.copy(), R=R, t=t))
            truth.videos.append(VideoCameras(name=camera.name, width=width, height=height, fps=fps, frames=frames))
            logging.info("rendered %s (%.0f s so far)", path, time.perf_counter() - started)
    write_cameras(truth_path, truth)
    return paths


def stage_table(report: dict, total_frames: int) -> list[tuple[str, float, int, str]]:
    """(stage, seconds, frames, what the frames are) per stage of a register report."""
    videos = report["videos"]
    sfm_frames = sum(v["sfm_frames"] for v in videos)
    rows = []
    counts = {
        "probe": (total_frames, "decoded"),
        "motion_test": (total_frames, "in the videos (24 sampled each)"),
        "keyframes": (total_frames, "decoded at 480 px"),
        "decode": (sfm_frames, "keyframes written"),
        "extract": (sfm_frames, "keyframes"),
        "match": (sfm_frames, f"keyframes ({report['pairs']} pairs)"),
        "map": (sfm_frames, "keyframes"),
        "localize": (total_frames - sfm_frames, "in-between"),
        "subject": (0, ""),
        "export": (total_frames, "written"),
    }
    for stage in STAGES:
        if stage in report["timings_s"]:
            frames, what = counts[stage]
            rows.append((stage, float(report["timings_s"][stage]), frames, what))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--out", type=Path, default=Path("/tmp/long_handheld"))
    parser.add_argument("--threads", type=int, default=-1, help="COLMAP threads (-1: all cores)")
    parser.add_argument("--workers", type=int, default=2, help="rendering processes")
    parser.add_argument("--check", action="store_true", help="compare the wall renderer with room.render first")
    parser.add_argument("--render-only", action="store_true", help="render the videos and stop")
    parser.add_argument("--keep", action="store_true", help="resume in the previous workspace instead of a new one")
    parser.add_argument("--max-frames", type=int, default=RegisterOptions().max_frames, help="keyframes per video")
    parser.add_argument(
        "--no-added-keyframes", action="store_true", help="tracking never promotes a frame to a keyframe"
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.check:
        print(f"render_walls vs room.render: mean |difference| {check_renderer():.2f} grey levels")
    width, height = (int(x) for x in args.size.split("x"))
    folder = args.out / f"videos_{args.seconds:g}s_{args.fps:g}fps_{width}x{height}"
    started = time.perf_counter()
    videos = render_capture(folder, args.seconds, args.fps, width, height, args.workers)
    print(f"videos ready in {time.perf_counter() - started:.0f} s: {folder}")
    if args.render_only:
        return 0
    if args.no_added_keyframes:  # chains never start fresh corners, so never promote a frame
        track_pose.FRESH_SURVIVAL = track_pose.PROMOTE_SURVIVAL = -1.0
    ws = args.out / f"ws_{args.seconds:g}s_{width}x{height}_{args.max_frames}"
    if not args.keep:
        shutil.rmtree(ws, ignore_errors=True)
    started, cpu = time.perf_counter(), _cpu_seconds()
    path = run_register(videos, ws, RegisterOptions(num_threads=args.threads, max_frames=args.max_frames))
    wall, cpu = time.perf_counter() - started, _cpu_seconds() - cpu
    report = json.loads((ws / "register_report.json").read_text())
    truth = read_cameras(folder / "truth_cameras.json")
    total = truth.num_frames
    registered = sum(v["registered"] for v in report["videos"])
    print(f"{len(videos)} videos x {args.seconds:g} s x {args.fps:g} fps at {width}x{height}: {total} frames")
    print("| stage | seconds | frames | frames/s | frames are |")
    print("|---|---|---|---|---|")
    for stage, seconds, frames, what in stage_table(report, total):
        rate = f"{frames / seconds:.1f}" if frames and seconds > 0 else "-"
        print(f"| {stage} | {seconds:.1f} | {frames} | {rate} | {what} |")
    print(f"| **total** | **{wall:.1f}** | {total} | {total / wall:.1f} | registered {registered}/{total} |")
    print(f"CPU s (with COLMAP children): {cpu:.1f}; localize wall {report['timings_s']['localize']}")
    for video in report["videos"]:
        keys = video["keyframes"] or {}
        print(
            f"{video['name']}: {video['registered']}/{video['frames_given']} registered, {video['sfm_frames']} "
            f"keyframes {keys.get('by_reason')}, tracked {video['registered_by_tracking']}, keyframes added "
            f"{video['keyframes_added']}, failed {sum(run['frames'] for run in video['failed'])}"
        )
    errors = compare(read_cameras(path), truth)
    print(
        f"centre error mean / max {1000 * errors.center_errors.mean():.1f} / {1000 * errors.center_errors.max():.1f} mm"
        f", rotation error mean / max {errors.rotation_errors_deg.mean():.3f} / {errors.rotation_errors_deg.max():.3f}"
        f" deg ({len(errors.keys)} frames); reused steps: {report['reused_steps']}"
    )
    _path_table(report, errors.keys, errors.center_errors, errors.rotation_errors_deg, total)
    return 0


def _path_table(report: dict, keys: list, centre: np.ndarray, rotation: np.ndarray, total: int) -> None:
    """Frames and their errors (after the similarity over all posed frames) per path that posed them."""
    path_of = {(v["name"], f): p["path"] for v in report["videos"] for f, p in posed_frames(v).items()}
    added = sum(v["keyframes_added"] for v in report["videos"])
    print(
        f"\n| path | frames | centre err median / mean / max (mm) | rotation err median / max (deg) |  (added {added})"
    )
    print("|---|---|---|---|")
    paths = np.array([path_of.get(tuple(k), "none") for k in keys])
    for path in ("sfm", "tracked", "sift"):
        chosen = paths == path
        if not chosen.any():
            print(f"| {path} | 0 | | |")
            continue
        c, r = 1000 * centre[chosen], rotation[chosen]
        print(
            f"| {path} | {chosen.sum()} | {np.median(c):.1f} / {c.mean():.1f} / {c.max():.1f} "
            f"| {np.median(r):.3f} / {r.max():.3f} |"
        )
    print(f"| none | {total - len(keys)} | | |")


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (COLMAP runs in child processes)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


if __name__ == "__main__":
    raise SystemExit(main())
