"""`dynrecon register` on the real static rigs in ../shared, against their own calibrations.

    python benchmarks/register_real.py [--cases NAME,...] [--work /tmp/register_real]

Cases (each a fresh workspace; `register` as a user runs it, with its defaults unless named):
- caliscope-background: the 4 office webcams, background only (`--subject never`), no calibration given;
- caliscope-background-intrinsics: the same with `--intrinsics camera_array.toml`;
- caliscope-subject: the ChArUco board's corners (OpenCV's aruco module) as the subject's tracks, the videos
  desynchronized by dropping different leading frames per camera, `--subject always`, no calibration given;
- caliscope-subject-intrinsics: the same with `--intrinsics camera_array.toml`;
- caliscope-auto: the desynchronized videos with the corner tracks, default options (background, then subject);
- pose2sim-background: the 4 lab cameras, background only;
- pose2sim-subject: the committed labels (tests/data/pose2sim) tracked through the videos, `--subject always`,
  with and without the lab intrinsics (`pose2sim-subject-intrinsics`).

Per case: videos posed and by which path, seconds per stage, and after a similarity to the rig's calibration
(rotation from the orientations, scale and shift from the centres: `sfm.evaluate.compare`) the worst centre error
in % of the camera spread and the worst rotation error in degrees; for the subject path, the recovered offsets
against the truth in frames (caliscope: its per-frame capture times; pose2sim: the videos are synchronized to
about a frame). Needs ../shared (exits with a message otherwise).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon
from sfm.calibration import read_calibration
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras
from sfm.evaluate import compare
from tracking.charuco import charuco_tracks
from tracking.tracks import write_tracks

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "videos"
CALISCOPE = SHARED / "caliscope_office"
POSE2SIM = SHARED / "pose2sim_demo"
LABELS = Path(__file__).resolve().parents[1] / "tests" / "data" / "pose2sim" / "labels.csv"
DROPPED = {"cam_0": 0, "cam_1": 4, "cam_2": 9, "cam_3": 2}  # leading frames dropped per camera (desync)
CASES = (
    "caliscope-background",
    "caliscope-background-intrinsics",
    "caliscope-subject",
    "caliscope-subject-intrinsics",
    "caliscope-auto",
    "pose2sim-background",
    "pose2sim-subject",
    "pose2sim-subject-intrinsics",
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
    return {
        "centre_pct": round(100 * float(errors.center_errors.max()) / spread, 2),
        "rotation_deg": round(float(errors.rotation_errors_deg.max()), 3),
    }


def desynchronized_caliscope(work: Path) -> list[Path]:
    """The office videos without their first DROPPED[name] frames (mp4v, same nominal rate)."""
    out = work / "caliscope_desync"
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, drop in DROPPED.items():
        target = out / f"{name}.mp4"
        paths.append(target)
        if target.exists():
            continue
        capture = cv2.VideoCapture(str(CALISCOPE / "calibration" / "extrinsic" / f"{name}.mp4"))
        fps = capture.get(cv2.CAP_PROP_FPS)
        writer = None
        index = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if index >= drop:
                if writer is None:
                    h, w = image.shape[:2]
                    writer = cv2.VideoWriter(str(target), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
                writer.write(image)
            index += 1
        capture.release()
        if writer is not None:
            writer.release()
    return paths


def caliscope_true_offsets() -> dict[str, float]:
    """Seconds: own time of a desynchronized video + offset = cam_0's clock, from the real capture times."""
    data = np.genfromtxt(CALISCOPE / "calibration" / "extrinsic" / "timestamps.csv", delimiter=",", names=True)
    offsets = {}
    for name, drop in DROPPED.items():
        rows = data[data["cam_id"] == int(name.split("_")[1])]
        rows = rows[np.argsort(rows["frame_index"])][drop:]
        own = np.arange(len(rows)) / 6.0  # the decoder's times of the resampled 6 fps video
        offsets[name] = float(np.median(rows["frame_time"] - own))
    reference = offsets["cam_0"]
    return {k: v - reference for k, v in offsets.items()}


def run_case(case: str, work: Path) -> dict[str, Any]:
    ws = work / case
    ws.mkdir(parents=True, exist_ok=True)
    for stale in ("cameras.json", "register_report.json", "tracks.csv"):
        (ws / stale).unlink(missing_ok=True)
    args: list[str] = []
    true_offsets: dict[str, float] | None = None
    frame_period = 1 / 6.0
    if case.startswith("caliscope"):
        truth = truth_cameras(CALISCOPE / "camera_array.toml", [f"cam_{i}" for i in range(4)])
        if "subject" in case or case == "caliscope-auto":
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
        if "intrinsics" in case:
            args += ["--intrinsics", str(POSE2SIM / "calibration" / "Calib.qca.txt")]
    if "background" in case:
        args += ["--subject", "never"]
    elif "subject" in case:
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
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--work", type=Path, default=Path("/tmp/register_real"))
    args = parser.parse_args(argv)
    if not CALISCOPE.exists() or not POSE2SIM.exists():
        print(f"needs the real videos in {SHARED}")
        return 1
    rows = [run_case(case, args.work) for case in args.cases.split(",")]
    print("\n| case | posed | centre err % spread | rotation err deg | offsets err (frames) | register s |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        posed = sum(1 for v in row["posed"].values() if v != "none")
        paths = ", ".join(f"{k}: {v}" for k, v in row["posed"].items())
        offsets = row.get("offset_error_frames")
        print(
            f"| {row['case']} | {posed}/4 ({paths}) | {row.get('centre_pct')} | {row.get('rotation_deg')} | "
            f"{offsets} | {row['wall_s']} |"
        )
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
