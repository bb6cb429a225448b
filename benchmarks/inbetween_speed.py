"""In-between frames: posed by tracking (`--inbetween track`) against SIFT per frame (`--inbetween sift`).

    python benchmarks/inbetween_speed.py [--cases sample,room720,room1080] [--sift-every 3] [--out /tmp/inbetween]

Per case, `register` runs once with `--localize none` (the SfM keyframes only); then `localize_all` poses every other
frame by tracking (timed: decoding, tracking, PnP and any SIFT fallback), and by SIFT every `--sift-every`-th of
them (timed). Both are compared with the ground truth on the frames both posed, after the similarity that maps the
SfM keyframes onto their true poses (the same for both paths). Cases:
- sample: the demo's videos (data_samples/video_sample, 480x360, 3 handheld cameras, no masks), 12 SfM frames each;
- room720 / room1080: the synthetic room (sfm/synthetic) seen by 2 handheld cameras at 1280x720 / 1920x1080,
  30 fps, the orbiting spheres masked from their true tracks, 6 SfM frames per video.
Prints markdown tables (speed, accuracy). CPU heavy: renders (cached in --out), registers, localizes.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pycolmap

from sfm import Localize, RegisterOptions
from sfm import register as run_register
from sfm.cameras import CameraSet, VideoCameras, read_cameras
from sfm.frames import Resize, image_name, select_frames
from sfm.localize_frames import localize_all
from sfm.masks import mask_from_points, track_points, write_mask
from sfm.options import InBetween
from sfm.plan import FramePose, VideoPlan
from sfm.synthetic.demo import render_demo, sphere_tracks, three_cameras
from sfm.video import probe_video
from tracking.tracks import Tracks, write_tracks

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data_samples" / "video_sample"
MASK_RADIUS = 60.0  # original pixels around the spheres' tracked centres (radius ~0.3 m at 2-4 m)


@dataclass(kw_only=True)
class Case:
    name: str
    videos: list[Path]
    truth: CameraSet
    tracks: Tracks | None
    max_frames: int
    long_side: int
    mm: float  # millimetres per unit of the truth


def _room_case(name: str, out: Path, width: int, height: int, frames: int) -> Case:
    folder = out / f"videos_{name}"
    cameras = three_cameras(width, height, frames=(frames, frames, frames), fps=(30.0, 30.0, 30.0))[:2]
    truth_path = folder / "truth_cameras.json"
    if not truth_path.exists():
        rendered = render_demo(folder, cameras)
        from sfm.cameras import write_cameras

        write_cameras(truth_path, CameraSet(videos=[v.cameras for v in rendered]))
        write_tracks(folder / "tracks.csv", sphere_tracks(rendered))
    from tracking.tracks import read_tracks

    return Case(
        name=name,
        videos=[folder / f"{c.name}.mp4" for c in cameras],
        truth=read_cameras(truth_path),
        tracks=read_tracks(folder / "tracks.csv"),
        max_frames=6,
        long_side=1280,
        mm=1000.0,
    )


def _sample_case() -> Case:
    return Case(
        name="sample",
        videos=[SAMPLE / f"cam{i}.mp4" for i in range(3)],
        truth=read_cameras(SAMPLE / "truth_cameras.json"),
        tracks=None,
        max_frames=12,
        long_side=1280,
        mm=1.0,
    )


def _plans(case: Case) -> list[VideoPlan]:
    plans = []
    for path in case.videos:
        info = probe_video(path)
        sfm_frames = select_frames(info, max_frames=case.max_frames)
        plans.append(
            VideoPlan(
                info=info,
                resize=Resize.for_video(info, case.long_side),
                sfm_frames=sfm_frames,
                wanted=np.arange(info.num_frames, dtype=np.int64),
            )
        )
    return plans


def _write_all_masks(case: Case, plans: list[VideoPlan], mask_dir: Path) -> None:
    """Masks for every frame (register wrote them only for the SfM frames with --localize none)."""
    if case.tracks is None:
        return
    for plan in plans:
        per_frame = track_points(case.tracks, plan.info.name)
        for frame, points in per_frame.items():
            mask = mask_from_points(points, plan.resize, MASK_RADIUS)
            write_mask(mask_dir, image_name(plan.info.name, frame), mask)


def _largest_model(ws: Path) -> pycolmap.Reconstruction:
    models = [pycolmap.Reconstruction(str(p)) for p in sorted((ws / "sfm" / "models").iterdir()) if p.is_dir()]
    return max(models, key=lambda r: r.num_reg_images())


def _localize(
    plans: list[VideoPlan], rec: pycolmap.Reconstruction, ws: Path, masked: bool, mode: InBetween
) -> tuple[dict[str, dict[int, FramePose]], float]:
    (ws / "sfm" / "localize.db").unlink(missing_ok=True)
    started = _cpu_seconds()
    results = localize_all(
        plans,
        rec,
        ws / "sfm" / "database.db",
        ws / "frames",
        ws / "sfm",
        ws / "sfm" / "masks" if masked else None,
        ws / "sfm" / "colmap.log",
        max_features=4096,
        max_ratio=0.8,
        min_inliers=30,
        num_threads=-1,
        inbetween=mode,
    )
    return results, _cpu_seconds() - started


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (COLMAP runs in child processes): on a machine
    shared with other work, the wall clock measures the others too."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _alignment(results: dict[str, dict[int, FramePose]], truth: CameraSet) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) mapping estimated world points onto the truth, from the SfM keyframes (as sfm.evaluate.compare)."""
    est_c, ref_c, rotations = [], [], []
    for name, per_frame in results.items():
        ref = {f.frame: f for f in truth.video(name).frames}
        for frame, pose in per_frame.items():
            if pose.source == "sfm" and pose.pose is not None:
                R = pose.pose.rotation.matrix()
                est_c.append(-R.T @ np.asarray(pose.pose.translation))
                ref_c.append(ref[frame].center)
                rotations.append(ref[frame].R.T @ R)
    U, _, Vt = np.linalg.svd(sum(rotations))
    R_align = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    rotated = np.array(est_c) @ R_align.T
    target = np.array(ref_c)
    a, b = rotated - rotated.mean(axis=0), target - target.mean(axis=0)
    s = float((a * b).sum() / (a * a).sum())
    return s, R_align, target.mean(axis=0) - s * rotated.mean(axis=0)


def _errors(
    pose: FramePose, truth: VideoCameras, frame: int, align: tuple[float, np.ndarray, np.ndarray]
) -> tuple[float, float]:
    """(centre error in metres, rotation error in degrees) of one frame against the truth."""
    assert pose.pose is not None
    s, R_align, t = align
    R = pose.pose.rotation.matrix()
    centre = s * R_align @ (-R.T @ np.asarray(pose.pose.translation)) + t
    ref = {f.frame: f for f in truth.frames}[frame]
    delta = R @ R_align.T @ ref.R.T
    angle = np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(centre - ref.center)), float(angle)


def run_case(case: Case, out: Path, sift_every: int, threads: int) -> dict[str, Any]:
    ws = out / f"ws_{case.name}"
    shutil.rmtree(ws, ignore_errors=True)
    options = RegisterOptions(
        max_frames=case.max_frames,
        long_side=case.long_side,
        localize=Localize.NONE,
        tracks=None,
        num_threads=threads,
    )
    if case.tracks is not None:
        write_tracks(ws / "tracks.csv", case.tracks)
        options.tracks = ws / "tracks.csv"
        options.mask_radius = MASK_RADIUS
    started = time.perf_counter()
    run_register([str(v) for v in case.videos], ws, options)
    sfm_seconds = time.perf_counter() - started
    rec = _largest_model(ws)
    plans = _plans(case)
    _write_all_masks(case, plans, ws / "sfm" / "masks")
    wall = time.perf_counter()
    tracked, track_seconds = _localize(plans, rec, ws, case.tracks is not None, InBetween.TRACK)
    track_wall = time.perf_counter() - wall
    for plan in plans:  # SIFT on every sift_every-th in-between frame: its cost is per frame
        inbetween = np.setdiff1d(plan.wanted, plan.sfm_frames)
        plan.wanted = np.union1d(plan.sfm_frames, inbetween[::sift_every])
    sift, sift_seconds = _localize(plans, rec, ws, case.tracks is not None, InBetween.SIFT)
    align = _alignment(tracked, case.truth)
    rows: dict[str, list[tuple[float, float]]] = {"tracked": [], "sift": []}
    paths = {"tracked": 0, "sift": 0, "none": 0}
    inbetween_total = 0
    for plan in plans:
        name = plan.info.name
        for frame, pose in tracked[name].items():
            if pose.source == "sfm":
                continue
            inbetween_total += 1
            paths["tracked" if pose.source == "tracked" else "sift" if pose.pose is not None else "none"] += 1
            other = sift[name].get(frame)
            if pose.source != "tracked" or other is None or other.pose is None:
                continue
            rows["tracked"].append(_errors(pose, case.truth.video(name), frame, align))
            rows["sift"].append(_errors(other, case.truth.video(name), frame, align))
    sift_frames = sum(1 for name in sift for p in sift[name].values() if p.source != "sfm")
    width, height = plans[0].info.width, plans[0].info.height
    return {
        "case": case.name,
        "size": f"{width}x{height}",
        "sfm_s": sfm_seconds,
        "inbetween": inbetween_total,
        "paths": paths,
        "track_fps": inbetween_total / track_seconds,
        "track_wall_fps": inbetween_total / track_wall,
        "sift_fps": sift_frames / sift_seconds if sift_seconds > 0 else float("nan"),
        "errors": {k: np.array(v).reshape(-1, 2) for k, v in rows.items()},
        "mm": case.mm,
    }


def _print(results: list[dict[str, Any]], threads: int) -> None:
    load = os.getloadavg()[0]
    print(
        f"\nSpeed: frames per CPU second (this process and its COLMAP children; one core's worth), and wall-clock "
        f"frames/s on the 2 shared cores (load average now {load:.1f}; COLMAP threads {threads})\n"
    )
    print(
        "| case | size | in-between frames | tracked / SIFT fallback / none | tracking: frames per CPU s "
        "| wall frames/s | SIFT: frames per CPU s |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in results:
        paths = r["paths"]
        print(
            f"| {r['case']} | {r['size']} | {r['inbetween']} | {paths['tracked']} / {paths['sift']} / {paths['none']} "
            f"| {r['track_fps']:.1f} | {r['track_wall_fps']:.1f} | {r['sift_fps']:.2f} |"
        )
    print("\nAccuracy on the frames both paths posed, against the truth (after the keyframes' similarity)\n")
    print(
        "| case | frames | centre err mean / max (mm): tracked | SIFT | ratio mean / max | rotation err mean / max "
        "(deg): tracked | SIFT | ratio mean / max |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        t, s = r["errors"]["tracked"], r["errors"]["sift"]
        if not len(t):
            print(f"| {r['case']} | 0 | | | | | | |")
            continue
        tc, sc = r["mm"] * t[:, 0], r["mm"] * s[:, 0]
        print(
            f"| {r['case']} | {len(t)} | {tc.mean():.2f} / {tc.max():.2f} | {sc.mean():.2f} / {sc.max():.2f} "
            f"| {tc.mean() / sc.mean():.2f} / {tc.max() / sc.max():.2f} "
            f"| {t[:, 1].mean():.4f} / {t[:, 1].max():.4f} | {s[:, 1].mean():.4f} / {s[:, 1].max():.4f} "
            f"| {t[:, 1].mean() / s[:, 1].mean():.2f} / {t[:, 1].max() / s[:, 1].max():.2f} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", default="sample,room720,room1080")
    parser.add_argument("--frames", type=int, default=60, help="frames per rendered room video")
    parser.add_argument("--sift-every", type=int, default=3)
    parser.add_argument("--threads", type=int, default=-1)
    parser.add_argument("--out", type=Path, default=Path("/tmp/inbetween"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    makers = {
        "sample": _sample_case,
        "room720": lambda: _room_case("room720", args.out, 1280, 720, args.frames),
        "room1080": lambda: _room_case("room1080", args.out, 1920, 1080, args.frames),
        "room480": lambda: _room_case("room480", args.out, 640, 480, args.frames),
    }
    results = []
    for name in args.cases.split(","):
        started = time.perf_counter()
        case = makers[name]()
        print(f"{name}: videos ready in {time.perf_counter() - started:.0f} s", flush=True)
        results.append(run_case(case, args.out, args.sift_every, args.threads))
        print(f"{name}: done in {time.perf_counter() - started:.0f} s", flush=True)
        _print(results[-1:], args.threads)
    _print(results, args.threads)


if __name__ == "__main__":
    main()
