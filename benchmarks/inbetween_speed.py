"""In-between frames: posed by tracking (`--inbetween track`) against SIFT per frame (`--inbetween sift`).

    python benchmarks/inbetween_speed.py [--cases sample,room720,room1080,walk720] [--sift-every 3]
        [--out /tmp/inbetween]

Per case, `register` runs once with `--localize none` (the SfM keyframes only); then `localize_all` poses every other
frame by tracking (timed: decoding, tracking, PnP and any SIFT fallback), once as before added keyframes (a chain
never promotes a frame) and once with them, and by SIFT every `--sift-every`-th of them (timed). Both are compared
with the ground truth on the frames both posed, after the similarity that maps the SfM keyframes onto their true
poses (the same for both paths). Cases:
- sample: the demo's videos (data_samples/video_sample, 480x360, 3 handheld cameras, no masks), 12 SfM frames each;
- room720 / room1080: the synthetic room (sfm/synthetic) seen by 2 handheld cameras at 1280x720 / 1920x1080,
  30 fps, the orbiting spheres masked from their true tracks, 6 SfM frames per video;
- walk720: a camera walking 4 m along the room at 1280x720 while its view sweeps 6 m across the far wall, and a
  wide camera near the middle; after SfM only the walker's first keyframe is kept (as when the mapper drops the
  rest, or a keyframe budget forced low), so the walk leaves all its keyframes.
Prints markdown tables (speed, accuracy, and before / after added keyframes). CPU heavy: renders (cached in --out),
registers, localizes.
"""

from __future__ import annotations

import argparse
import json
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

from sfm import Localize, RegisterOptions, track_pose
from sfm import register as run_register
from sfm.cameras import CameraSet, VideoCameras, read_cameras
from sfm.frames import Resize, image_name, select_frames
from sfm.localize_frames import localize_all
from sfm.masks import mask_from_points, track_points, write_mask
from sfm.options import InBetween
from sfm.plan import FramePose, VideoPlan
from sfm.synthetic.demo import render_demo, sphere_tracks, three_cameras
from sfm.synthetic.scene import CameraPath
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
    only_first_keyframe: str | None = None  # this video keeps only its first registered keyframe after SfM


def walk_cameras(width: int, height: int, frames: int) -> list[CameraPath]:
    """A camera walking 4 m along the near side while its view sweeps 6 m across the far wall, and a wide one."""
    paths = []
    setups = [  # (focal / width, start, end, target at start, target at end)
        (0.78, [1.5, 0.8, 1.5], [5.5, 1.0, 1.6], [1.0, 6.0, 1.3], [7.0, 6.0, 1.5]),
        (0.55, [4.0, 0.4, 1.7], [4.4, 0.5, 1.7], [3.0, 6.0, 1.2], [5.0, 6.0, 1.2]),
    ]
    for index, (focal, start, end, target, target_end) in enumerate(setups):
        f = focal * width
        K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
        paths.append(
            CameraPath(
                name=f"cam{index}",
                K=K,
                width=width,
                height=height,
                fps=30.0,
                num_frames=frames,
                start=np.array(start),
                end=np.array(end),
                target_start=np.array(target),
                target_end=np.array(target_end),
            )
        )
    return paths


def _room_case(name: str, out: Path, width: int, height: int, frames: int, walk: bool = False) -> Case:
    folder = out / f"videos_{name}"
    if walk:
        cameras = walk_cameras(width, height, frames)
    else:
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
        only_first_keyframe="cam0" if walk else None,
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


def _plans(case: Case, ws: Path) -> list[VideoPlan]:
    """Every frame wanted; the SfM frames are those register chose (by content, or evenly when content chose too
    few)."""
    report = json.loads((ws / "register_report.json").read_text())
    chosen = {v["name"]: v["keyframes"]["frames"] for v in report["videos"] if v["keyframes"]}
    plans = []
    for path in case.videos:
        info = probe_video(path)
        if info.name in chosen:
            sfm_frames = np.asarray(chosen[info.name], dtype=np.int64)
        else:
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


def _model_results(rec: pycolmap.Reconstruction) -> dict[str, dict[int, FramePose]]:
    """The model's registered images as SfM poses: video -> frame -> FramePose."""
    results: dict[str, dict[int, FramePose]] = {}
    for image in rec.images.values():
        if image.has_pose:
            video, name = image.name.split("/")
            results.setdefault(video, {})[int(Path(name).stem)] = FramePose(pose=image.cam_from_world(), source="sfm")
    return results


def _only_first_keyframe(rec: pycolmap.Reconstruction, video: str) -> None:
    """Deregister every keyframe of `video` but its first, as if the mapper had kept only that one."""
    images = sorted(
        (image for image in rec.images.values() if image.name.startswith(f"{video}/") and image.has_pose),
        key=lambda image: image.name,
    )
    for image in images[1:]:
        rec.deregister_frame(image.frame_id)


def _localize(
    plans: list[VideoPlan],
    rec: pycolmap.Reconstruction,
    ws: Path,
    masked: bool,
    mode: InBetween,
    added_keyframes: bool = True,
) -> tuple[dict[str, dict[int, FramePose]], float]:
    (ws / "sfm" / "localize.db").unlink(missing_ok=True)
    saved = track_pose.FRESH_SURVIVAL
    if not added_keyframes:  # before added keyframes: a chain never starts fresh corners, so never promotes
        track_pose.FRESH_SURVIVAL = -1.0
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
    track_pose.FRESH_SURVIVAL = saved
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
    align = _alignment(_model_results(rec), case.truth)  # every registered keyframe, before any is dropped
    if case.only_first_keyframe is not None:
        _only_first_keyframe(rec, case.only_first_keyframe)
    plans = _plans(case, ws)
    _write_all_masks(case, plans, ws / "sfm" / "masks")
    before, before_seconds = _localize(plans, rec, ws, case.tracks is not None, InBetween.TRACK, False)
    wall = time.perf_counter()
    tracked, track_seconds = _localize(plans, rec, ws, case.tracks is not None, InBetween.TRACK)
    track_wall = time.perf_counter() - wall
    for plan in plans:  # SIFT on every sift_every-th in-between frame: its cost is per frame
        inbetween = np.setdiff1d(plan.wanted, plan.sfm_frames)
        plan.wanted = np.union1d(plan.sfm_frames, inbetween[::sift_every])
    sift, sift_seconds = _localize(plans, rec, ws, case.tracks is not None, InBetween.SIFT)
    rows: dict[str, list[tuple[float, float]]] = {"tracked": [], "sift": []}
    paths = {"tracked": 0, "sift": 0, "none": 0}
    inbetween_total = 0
    for plan in plans:
        name = plan.info.name
        for frame, pose in tracked[name].items():
            if pose.source == "sfm":
                continue
            inbetween_total += 1
            paths[_path(pose)] += 1
            other = sift[name].get(frame)
            if _path(pose) != "tracked" or other is None or other.pose is None:
                continue
            rows["tracked"].append(_errors(pose, case.truth.video(name), frame, align))
            rows["sift"].append(_errors(other, case.truth.video(name), frame, align))
    sift_frames = sum(1 for name in sift for p in sift[name].values() if p.source != "sfm")
    modes = {
        "before": _mode_summary(before, before_seconds, case.truth, align),
        "after": _mode_summary(tracked, track_seconds, case.truth, align),
        "sift": _mode_summary(sift, sift_seconds, case.truth, align),
    }
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
        "modes": modes,
    }


def _path(pose: FramePose) -> str:
    """tracked (from a model keyframe or an added one), sift or none."""
    if pose.pose is None:
        return "none"
    return "tracked" if pose.source is not None and pose.source.startswith("tracked") else "sift"


def _mode_summary(
    results: dict[str, dict[int, FramePose]],
    seconds: float,
    truth: CameraSet,
    align: tuple[float, np.ndarray, np.ndarray],
) -> dict[str, Any]:
    """In-between frames per path, keyframes added, CPU seconds, (frame key -> (centre m, rotation deg)), and the
    frame keys posed by tracking."""
    paths = {"tracked": 0, "sift": 0, "none": 0}
    errors = {}
    tracked = set()
    added = 0
    for name, per_frame in results.items():
        for frame, pose in per_frame.items():
            if pose.source == "sfm":
                continue
            paths[_path(pose)] += 1
            added += pose.source == "tracked (added keyframe)"
            if pose.pose is not None:
                errors[(name, frame)] = _errors(pose, truth.video(name), frame, align)
            if _path(pose) == "tracked":
                tracked.add((name, frame))
    return {"paths": paths, "added": added, "seconds": seconds, "errors": errors, "tracked": tracked}


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


def _print_modes(results: list[dict[str, Any]]) -> None:
    print("\nBefore / after added keyframes (tracking, SIFT where it fails): in-between frames per path, errors of")
    print("all posed in-between frames and of those that only `after` posed by tracking (the far frames)\n")
    print(
        "| case | mode | tracked / SIFT / none | keyframes added | CPU s | centre err median / max (mm) "
        "| rotation err median / max (deg) | far frames: centre median / max (mm), rotation max (deg) "
        "| / SIFT's on the frames both posed by tracking and SIFT: centre, rotation mean (frames) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        before, after, sift = r["modes"]["before"], r["modes"]["after"], r["modes"]["sift"]["errors"]
        far = [k for k in after["errors"] if k not in before["errors"]]
        for mode, summary in (("before", before), ("after", after)):
            paths = summary["paths"]
            e = np.array(list(summary["errors"].values())).reshape(-1, 2)
            f = np.array([summary["errors"][k] for k in far if k in summary["errors"]]).reshape(-1, 2)
            c, fc = r["mm"] * e[:, 0], r["mm"] * f[:, 0]
            far_text = f"{np.median(fc):.1f} / {fc.max():.1f}, {f[:, 1].max():.3f} ({len(f)})" if len(f) else "-"
            both = [k for k in summary["errors"] if k in sift and k in summary["tracked"]]
            mine = np.array([summary["errors"][k] for k in both]).reshape(-1, 2)
            theirs = np.array([sift[k] for k in both]).reshape(-1, 2)
            ratio = mine.mean(axis=0) / theirs.mean(axis=0) if both else np.full(2, np.nan)
            print(
                f"| {r['case']} | {mode} | {paths['tracked']} / {paths['sift']} / {paths['none']} | {summary['added']} "
                f"| {summary['seconds']:.1f} | {np.median(c):.2f} / {c.max():.2f} "
                f"| {np.median(e[:, 1]):.4f} / {e[:, 1].max():.4f} | {far_text} "
                f"| {ratio[0]:.2f}, {ratio[1]:.2f} ({len(both)}) |"
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
        "walk720": lambda: _room_case("walk720", args.out, 1280, 720, args.frames, walk=True),
    }
    results = []
    for name in args.cases.split(","):
        started = time.perf_counter()
        case = makers[name]()
        print(f"{name}: videos ready in {time.perf_counter() - started:.0f} s", flush=True)
        results.append(run_case(case, args.out, args.sift_every, args.threads))
        print(f"{name}: done in {time.perf_counter() - started:.0f} s", flush=True)
        _print(results[-1:], args.threads)
        _print_modes(results[-1:])
    _print(results, args.threads)
    _print_modes(results)


if __name__ == "__main__":
    main()
