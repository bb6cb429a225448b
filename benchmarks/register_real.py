"""`dynrecon register` on the real static rigs in ../shared, against their own calibrations.

    python benchmarks/register_real.py [--cases NAME,...] [--work /tmp/register_real] [--caliscope SESSION]

Cases (each a fresh workspace; `register` as a user runs it, with its defaults unless named):
- caliscope-background: the 4 office webcams, background only (`--subject never`), no calibration given;
- caliscope-background-intrinsics: the same with `--intrinsics camera_array.toml`;
- caliscope-subject: the ChArUco board's corners (OpenCV's aruco module) as the subject's tracks, the videos
  desynchronized by dropping different leading frames per camera, `--subject always`, no calibration given;
- caliscope-subject-intrinsics: the same with `--intrinsics camera_array.toml`;
- caliscope-subject-board: the same without intrinsics but with `--board charuco.toml`: each camera's intrinsics
  from its own board views, and the metric scale from the board's corner spacing;
- caliscope-subject-intrinsics-scale: `--intrinsics camera_array.toml` and `--scale` on the board's two farthest
  corners: the rig's own intrinsics, scored like the board case (`board_mm`);
- caliscope-auto: the desynchronized videos with the corner tracks, default options (background, then subject);
- caliscope-markers: the desynchronized videos and nothing else (no tracks, no calibration, default options): the
  background leaves videos out, and `register` takes the board's ArUco markers it finds as the subject's tracks;
  `caliscope-markers-intrinsics` the same with `--intrinsics camera_array.toml`;
- pose2sim-background: the 4 lab cameras, background only;
- pose2sim-subject: the committed labels (tests/data/pose2sim) tracked through the videos, `--subject always`,
  with and without the lab intrinsics (`pose2sim-subject-intrinsics`);
- pose2sim-openpose: the committed OpenPose detections (tests/data/pose2sim/openpose_tracks.csv), the videos and
  the detections desynchronized by dropping different leading frames per camera, `--subject always`, with and
  without the lab intrinsics (`pose2sim-openpose-intrinsics`);
- pose2sim-openpose-markers-intrinsics: the same desynchronized videos and detections, plus the committed labels
  (renumbered like the frames; labels on dropped frames left out) tracked through the desynchronized videos, with
  the lab intrinsics: the user's few precise markers next to the detections;
- pose2sim-openpose-names-intrinsics: the same desynchronized detections with the lab intrinsics, but without the
  videos: each given by its name with `--fps 60` (detections shared without their footage);
- caliscope-mediapipe-intrinsics, pose2sim-mediapipe-intrinsics: another detector on both rigs: MediaPipe Pose's 33
  keypoints of the person (committed tests/data/*/mediapipe_tracks.csv, made by benchmarks/mediapipe_tracks.py) on
  the original videos, with the rig's intrinsics, `--subject always`;
- `--caliscope SESSION`: the caliscope cases on another four-camera caliscope session folder (its
  camera_array.toml, charuco.toml, calibration/extrinsic/cam_0.mp4 ... cam_3.mp4 and timestamps.csv, with or
  without a frame_index column), such as the other recordings of the same office in caliscope's repository
  (tests/sessions/post_optimization, tests/sessions/4_cam_recording): recordings this project was not built on.
- caliscope-plain: not dynrecon: plain pycolmap defaults (5 frames per video, exhaustive matching, incremental
  mapping), the simpler method a user would try first; its models are scored pair by pair (relative rotation,
  and the direction of the baseline seen from the first camera), since it splits the videos over models.

Per case: videos posed and by which path, seconds per stage, and after a similarity to the rig's calibration
(rotation from the orientations, scale and shift from the centres: `sfm.evaluate.compare`) the worst centre error
in % of the camera spread and the worst rotation error in degrees, and the rig's size over the true one's before
the similarity (1 when the units are metres); for the subject path, the recovered offsets
against the truth in frames (caliscope: its per-frame capture times; pose2sim: the videos are synchronized to
about a frame). For the caliscope cases whose cameras are in metres (`--board`), also the sync-free solve of the
corners on those cameras, scored by the board's geometry (`board_mm`: errors of the distances between corners seen
together). Needs ../shared (exits with a message otherwise).
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon
from reconstruct.outputs.points import read_points
from sfm.calibration import read_calibration
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras
from sfm.evaluate import compare
from tracking.charuco import board_corner_positions, charuco_tracks
from tracking.tracks import write_tracks

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "videos"
CALISCOPE = SHARED / "caliscope_office"
POSE2SIM = SHARED / "pose2sim_demo"
LABELS = Path(__file__).resolve().parents[1] / "tests" / "data" / "pose2sim" / "labels.csv"
OPENPOSE = LABELS.parent / "openpose_tracks.csv"
# MediaPipe Pose keypoints of the original videos (benchmarks/mediapipe_tracks.py; tests/data/*/README.md)
MEDIAPIPE = {
    "caliscope": LABELS.parents[1] / "caliscope" / "mediapipe_tracks.csv",
    "pose2sim": LABELS.parent / "mediapipe_tracks.csv",
}
DROPPED = {"cam_0": 0, "cam_1": 4, "cam_2": 9, "cam_3": 2}  # leading frames dropped per camera (desync)
DROPPED_POSE2SIM = {"cam01": 0, "cam02": 3, "cam03": 7, "cam04": 1}
CASES = (
    "caliscope-background",
    "caliscope-background-intrinsics",
    "caliscope-subject",
    "caliscope-subject-intrinsics",
    "caliscope-subject-board",
    "caliscope-subject-intrinsics-scale",
    "caliscope-auto",
    "caliscope-markers",
    "caliscope-markers-intrinsics",
    "pose2sim-background",
    "pose2sim-subject",
    "pose2sim-subject-intrinsics",
    "pose2sim-openpose",
    "pose2sim-openpose-intrinsics",
    "pose2sim-openpose-markers-intrinsics",
    "pose2sim-openpose-names-intrinsics",
    "caliscope-mediapipe-intrinsics",
    "pose2sim-mediapipe-intrinsics",
    "caliscope-plain",
)


def truth_cameras(calibration: Path, names: list[str]) -> CameraSet:
    """One frame (0) per camera of the calibration file, named after the videos in order."""
    cameras = read_calibration(calibration)
    by_name = {c.name: c for c in cameras}
    truth = CameraSet()
    for index, name in enumerate(names):
        camera = by_name.get(name, cameras[index])
        assert camera.R is not None and camera.t is not None
        truth.videos.append(
            VideoCameras(
                name=name,
                width=camera.width,
                height=camera.height,
                frames=[FrameCamera(frame=0, K=camera.K, R=camera.R, t=camera.t)],
            )
        )
    return truth


def score(cameras: CameraSet, truth: CameraSet) -> dict[str, Any]:
    """Worst centre error (% of the true camera spread) and rotation error (deg) over the posed videos."""
    first = CameraSet(
        videos=[
            VideoCameras(name=v.name, width=v.width, height=v.height, frames=v.frames[:1])
            for v in cameras.videos
            if v.frames
        ]
    )
    for video in first.videos:
        video.frames = [FrameCamera(frame=0, K=f.K, R=f.R, t=f.t) for f in video.frames]
    if len(first.videos) < 3:
        return {"centre_pct": None, "rotation_deg": None}
    errors = compare(first, truth)
    centres = np.array([v.frames[0].center for v in truth.videos])
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max() * 2)
    found = np.array([v.frames[0].center for v in first.videos])
    true = np.array([truth.video(v.name).frames[0].center for v in first.videos])
    return {
        "centre_pct": round(100 * float(errors.center_errors.max()) / spread, 2),
        "rotation_deg": round(float(errors.rotation_errors_deg.max()), 3),
        # the found rig's size over the true one's, before any similarity: 1 when the units are metres
        "size_ratio": round(_size(found) / _size(true), 4),
    }


def _size(centres: np.ndarray) -> float:
    return float(np.linalg.norm(centres[:, None] - centres[None], axis=2).mean())


def desynchronized(sources: dict[str, Path], dropped: dict[str, int], out: Path) -> list[Path]:
    """The videos without their first dropped[name] frames (mp4v, same nominal rate), in out/."""
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, source in sources.items():
        target = out / f"{name}.mp4"
        paths.append(target)
        if target.exists():
            continue
        capture = cv2.VideoCapture(str(source))
        fps = capture.get(cv2.CAP_PROP_FPS)
        writer = None
        index = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if index >= dropped[name]:
                if writer is None:
                    h, w = image.shape[:2]
                    writer = cv2.VideoWriter(str(target), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
                writer.write(image)
            index += 1
        capture.release()
        if writer is not None:
            writer.release()
    return paths


def desynchronized_caliscope(work: Path) -> list[Path]:
    """The office videos without their first DROPPED[name] frames."""
    sources = {name: CALISCOPE / "calibration" / "extrinsic" / f"{name}.mp4" for name in DROPPED}
    return desynchronized(sources, DROPPED, work / f"{CALISCOPE.name}_desync")


def desynchronized_pose2sim(work: Path) -> tuple[list[Path], Path]:
    """The lab videos without their first DROPPED_POSE2SIM[name] frames, and the OpenPose tracks renumbered to
    match (rows of dropped frames left out)."""
    sources = {name: POSE2SIM / "videos" / f"{name}.mp4" for name in DROPPED_POSE2SIM}
    videos = desynchronized(sources, DROPPED_POSE2SIM, work / "pose2sim_desync")
    tracks = work / "pose2sim_desync" / "openpose_tracks.csv"
    with OPENPOSE.open(newline="", encoding="utf-8") as source, tracks.open("w", newline="", encoding="utf-8") as out:
        reader = csv.DictReader(source)
        writer = csv.DictWriter(out, fieldnames=list(reader.fieldnames or []), lineterminator="\n")
        writer.writeheader()
        for row in reader:
            frame = int(row["frame"]) - DROPPED_POSE2SIM[row["video"]]
            if frame >= 0:
                writer.writerow({**row, "frame": str(frame)})
    return videos, tracks


def desynchronized_labels(out: Path) -> Path:
    """The committed labels renumbered like desynchronized_pose2sim's frames (labels on dropped frames left out)."""
    with LABELS.open(newline="", encoding="utf-8") as source, out.open("w", newline="", encoding="utf-8") as target:
        reader = csv.DictReader(source)
        writer = csv.DictWriter(target, fieldnames=list(reader.fieldnames or []), lineterminator="\n")
        writer.writeheader()
        for row in reader:
            frame = int(row["frame"]) - DROPPED_POSE2SIM[row["video"]]
            if frame >= 0:
                writer.writerow({**row, "frame": str(frame)})
    return out


def caliscope_true_offsets() -> dict[str, float]:
    """Seconds: own time of a desynchronized video + offset = cam_0's clock, from the real capture times."""
    data = np.genfromtxt(CALISCOPE / "calibration" / "extrinsic" / "timestamps.csv", delimiter=",", names=True)
    # older sessions have no frame_index: a camera's rows are its frames in capture order
    order = "frame_index" if "frame_index" in (data.dtype.names or ()) else "frame_time"
    offsets = {}
    for name, drop in DROPPED.items():
        rows = data[data["cam_id"] == int(name.split("_")[1])]
        rows = rows[np.argsort(rows[order])][drop:]
        own = np.arange(len(rows)) / 6.0  # the decoder's times of the resampled 6 fps video
        offsets[name] = float(np.median(rows["frame_time"] - own))
    reference = offsets["cam_0"]
    return {k: v - reference for k, v in offsets.items()}


def run_case(case: str, work: Path) -> dict[str, Any]:
    if case == "caliscope-plain":
        return plain_pycolmap(work / case)
    ws = work / case
    ws.mkdir(parents=True, exist_ok=True)
    for stale in ("cameras.json", "register_report.json", "tracks.csv", "marker_tracks.csv"):
        (ws / stale).unlink(missing_ok=True)
    args: list[str] = []
    true_offsets: dict[str, float] | None = None
    frame_period = 1 / 6.0
    if case.startswith("caliscope"):
        truth = truth_cameras(CALISCOPE / "camera_array.toml", [f"cam_{i}" for i in range(4)])
        if "mediapipe" in case:  # the original videos, captured together: offsets 0
            videos = [CALISCOPE / "calibration" / "extrinsic" / f"cam_{i}.mp4" for i in range(4)]
            (ws / "tracks.csv").write_bytes(MEDIAPIPE["caliscope"].read_bytes())
            tracking_s = 0.0
            true_offsets = {v.stem: 0.0 for v in videos}
        elif "markers" in case:  # nothing but the desynchronized videos: register finds the markers itself
            videos = desynchronized_caliscope(work)
            tracking_s = 0.0
            true_offsets = caliscope_true_offsets()
        elif "subject" in case or case == "caliscope-auto":
            videos = desynchronized_caliscope(work)
            started = time.perf_counter()
            write_tracks(ws / "tracks.csv", charuco_tracks(videos, CALISCOPE / "charuco.toml"))
            tracking_s = time.perf_counter() - started
            true_offsets = caliscope_true_offsets()
        else:
            videos = [CALISCOPE / "calibration" / "extrinsic" / f"cam_{i}.mp4" for i in range(4)]
            tracking_s = 0.0
        if "intrinsics" in case:
            args += ["--intrinsics", str(CALISCOPE / "camera_array.toml")]
        if "board" in case:
            args += ["--board", str(CALISCOPE / "charuco.toml")]
        if case.endswith("-scale"):  # the board's two farthest corners, as --board would take them
            args += ["--scale", "corner_0,corner_11,0.1947"]
    else:
        truth = truth_cameras(POSE2SIM / "calibration" / "Calib.qca.txt", [f"cam0{i}" for i in range(1, 5)])
        videos = [POSE2SIM / "videos" / f"cam0{i}.mp4" for i in range(1, 5)]
        frame_period = 1 / 60.0
        tracking_s = 0.0
        if "subject" in case:
            from tracking import stage as track_stage

            (ws / "labels.csv").write_bytes(LABELS.read_bytes())
            started = time.perf_counter()
            track_stage.run(ws, ws / "tracks.csv", videos={v.stem: v for v in videos})
            tracking_s = time.perf_counter() - started
            true_offsets = {v.stem: 0.0 for v in videos}  # synchronized to about a frame
        elif "mediapipe" in case:
            (ws / "tracks.csv").write_bytes(MEDIAPIPE["pose2sim"].read_bytes())
            true_offsets = {v.stem: 0.0 for v in videos}
        elif "openpose" in case:
            videos, tracks = desynchronized_pose2sim(work)
            (ws / "tracks.csv").write_bytes(tracks.read_bytes())
            if "markers" in case:
                from benchmarks.pose2sim_check import union_tracks
                from tracking import stage as track_stage
                from tracking.tracks import read_tracks

                desynchronized_labels(ws / "labels.csv")
                started = time.perf_counter()
                track_stage.run(ws, ws / "markers.csv", videos={v.stem: v for v in videos})
                tracking_s = time.perf_counter() - started
                write_tracks(ws / "tracks.csv", union_tracks(read_tracks(tracks), read_tracks(ws / "markers.csv")))
            # global = own + offset; the originals are synchronized to about a frame
            true_offsets = {name: drop / 60.0 for name, drop in DROPPED_POSE2SIM.items()}
        if "intrinsics" in case:
            args += ["--intrinsics", str(POSE2SIM / "calibration" / "Calib.qca.txt")]
    if "names" in case:  # the videos are not here: names, their frames the tracks' at the lab's 60 fps
        videos = [Path(v.stem) for v in videos]
        args += ["--fps", str(round(1 / frame_period))]
    if "background" in case:
        args += ["--subject", "never"]
    elif "subject" in case or "openpose" in case or "mediapipe" in case:
        args += ["--subject", "always"]
    started = time.perf_counter()
    code = dynrecon(["register", *(str(v) for v in videos), "--out", str(ws), *args])
    wall = time.perf_counter() - started
    report = json.loads((ws / "register_report.json").read_text())
    row: dict[str, Any] = {
        "case": case,
        "exit": code,
        "wall_s": round(wall, 1),
        "tracking_s": round(tracking_s, 1),
        "timings_s": report["timings_s"],
        "posed": {v["name"]: v["posed_by"] for v in report["videos"]},
        "static": {v["name"]: v["camera"] for v in report["videos"]},
    }
    if code == 0:
        row.update(score(read_cameras(ws / "cameras.json"), truth))
    subject = report.get("subject") or {}
    if true_offsets is not None and subject.get("cameras"):
        found = {c["name"]: c["offset_s"] for c in subject["cameras"]}
        names = [n for n in true_offsets if n in found]
        if names:
            ref = names[0]
            row["offset_error_frames"] = {
                n: round(((found[n] - found[ref]) - (true_offsets[n] - true_offsets[ref])) / frame_period, 2)
                for n in names
            }
        row["pairs"] = [(p["videos"], p["runner_up_ratio"], p["degenerate"]) for p in subject.get("pairs", [])]
    if code == 0 and case.startswith("caliscope") and "subject" in case:
        # arbitrary units: scored after one scale fitted to the board (marked "scaled")
        metric = bool(subject.get("metric"))
        row["board_mm"] = board_distance_errors(ws, fit_scale=not metric) | ({} if metric else {"scaled": True})
    return row


def board_distance_errors(ws: Path, fit_scale: bool = False) -> dict[str, float]:
    """The sync-free solve (`dynrecon solve`, defaults) of the corner tracks on the registered cameras, scored by
    the board's known geometry: |distance between two corners a video observed in one frame - their distance on
    the board|, mm, over every such pair (the solve's metres come from registration's scale; with `fit_scale`, for
    cameras in arbitrary units, the distances are first scaled by the median ratio of true to found)."""
    out = ws / "solve"
    inputs = ["--cameras", str(ws / "cameras.json"), "--tracks", str(ws / "tracks.csv")]
    code = dynrecon(["solve", *inputs, "--out", str(out), "--no-recording"])
    if code != 0:
        return {}
    points = read_points(out / "points3d.csv")
    positions = board_corner_positions(CALISCOPE / "charuco.toml")
    true = np.array([positions.get(name, np.full(3, np.nan)) for name in points.point_names])
    found_d, true_d = [], []
    for xyz, observed in zip(points.xyz, points.observed.astype(bool), strict=True):
        seen = np.flatnonzero(observed & np.isfinite(xyz).all(axis=1) & np.isfinite(true).all(axis=1))
        if seen.size < 2:
            continue
        a, b = np.triu_indices(seen.size, 1)
        found_d.append(np.linalg.norm(xyz[seen[a]] - xyz[seen[b]], axis=1))
        true_d.append(np.linalg.norm(true[seen[a]] - true[seen[b]], axis=1))
    if not found_d:
        return {}
    found_all, true_all = np.concatenate(found_d), np.concatenate(true_d)
    if fit_scale:
        found_all = found_all * float(np.median(true_all / found_all))
    every = 1000.0 * np.abs(found_all - true_all)
    return {"median": round(float(np.median(every)), 2), "p90": round(float(np.percentile(every, 90)), 2)}


def plain_models(ws: Path, per_video: int = 5) -> dict[int, Any]:
    """pycolmap's defaults on `per_video` evenly spaced frames of each office video (one camera per image, as a
    user's first try): its models, by index."""
    import pycolmap

    shutil.rmtree(ws, ignore_errors=True)
    images = ws / "images"
    images.mkdir(parents=True)
    for name in [f"cam_{i}" for i in range(4)]:
        capture = cv2.VideoCapture(str(CALISCOPE / "calibration" / "extrinsic" / f"{name}.mp4"))
        frames = []
        while True:
            ok, image = capture.read()
            if not ok:
                break
            frames.append(image)
        capture.release()
        for index in np.linspace(0, len(frames) - 1, per_video).round().astype(int):
            cv2.imwrite(str(images / f"{name}_{index:04d}.jpg"), frames[index])
    database = ws / "database.db"
    pycolmap.extract_features(database, images, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    return dict(pycolmap.incremental_mapping(database, images, ws / "sparse"))


def plain_pycolmap(ws: Path, per_video: int = 5) -> dict[str, Any]:
    """`plain_models`, scored pair by pair within each model against camera_array.toml."""
    names = [f"cam_{i}" for i in range(4)]
    started = time.perf_counter()
    models = plain_models(ws, per_video)
    wall = time.perf_counter() - started
    truth = {c.name: c for c in read_calibration(CALISCOPE / "camera_array.toml")}
    posed: dict[str, str] = {name: "none" for name in names}
    pairs = []
    for index, model in models.items():
        by_video: dict[str, Any] = {}
        for image in model.images.values():
            by_video.setdefault(image.name[:5], image)  # static cameras: one image stands for its video
        for name in by_video:
            posed[name] = f"model {index}" if posed[name] == "none" else posed[name]
        videos = sorted(by_video)
        for n, a in enumerate(videos):
            for b in videos[n + 1 :]:
                pairs.append(_pair_errors(a, b, by_video[a].cam_from_world(), by_video[b].cam_from_world(), truth))
    return {
        "case": "caliscope-plain",
        "exit": 0,
        "wall_s": round(wall, 1),
        "posed": posed,
        "pairs_vs_truth": pairs,
        "rotation_deg": max((p["rotation_deg"] for p in pairs), default=None),
        "baseline_direction_deg": max((p["baseline_direction_deg"] for p in pairs), default=None),
    }


def _pair_errors(a: str, b: str, pose_a: Any, pose_b: Any, truth: dict[str, Any]) -> dict[str, Any]:
    """Relative rotation error and the error of the baseline's direction seen from camera a (degrees)."""
    Ra, Rb = pose_a.rotation.matrix(), pose_b.rotation.matrix()
    ca, cb = -Ra.T @ pose_a.translation, -Rb.T @ pose_b.translation
    true_a, true_b = truth[a], truth[b]
    delta = (Rb @ Ra.T) @ (true_b.R @ true_a.R.T).T
    seen = Ra @ (cb - ca)
    true_seen = true_a.R @ (true_b.center - true_a.center)
    cosine = seen @ true_seen / (np.linalg.norm(seen) * np.linalg.norm(true_seen))
    return {
        "videos": [a, b],
        "rotation_deg": round(float(np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1)))), 2),
        "baseline_direction_deg": round(float(np.degrees(np.arccos(np.clip(cosine, -1, 1)))), 2),
    }


def main(argv: list[str] | None = None) -> int:
    global CALISCOPE  # the caliscope cases' session (--caliscope)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--work", type=Path, default=Path("/tmp/register_real"))
    parser.add_argument("--caliscope", type=Path, default=CALISCOPE, help="a caliscope session folder")
    args = parser.parse_args(argv)
    CALISCOPE = args.caliscope.resolve()
    if not CALISCOPE.exists() or not POSE2SIM.exists():
        print(f"needs the real videos in {SHARED} (and {CALISCOPE})")
        return 1
    needed = [CALISCOPE / "calibration" / "extrinsic" / f"{n}.mp4" for n in DROPPED]
    needed.append(CALISCOPE / "calibration" / "extrinsic" / "timestamps.csv")
    missing = [str(p) for p in needed if not p.is_file()]
    if missing and any(case.startswith("caliscope") for case in args.cases.split(",")):
        # the cases desynchronize cam_0-cam_3 by DROPPED and score the offsets with the capture times
        print(f"the caliscope cases need a four-camera session with its capture times; missing: {', '.join(missing)}")
        return 1
    rows = [run_case(case, args.work) for case in args.cases.split(",")]
    print("\n| case | posed | centre err % spread | rotation err deg | offsets err (frames) | board mm | register s |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        posed = sum(1 for v in row["posed"].values() if v != "none")
        paths = ", ".join(f"{k}: {v}" for k, v in row["posed"].items())
        offsets = row.get("offset_error_frames")
        print(
            f"| {row['case']} | {posed}/4 ({paths}) | {row.get('centre_pct')} | {row.get('rotation_deg')} | "
            f"{offsets} | {row.get('board_mm', '')} | {row['wall_s']} |"
        )
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
