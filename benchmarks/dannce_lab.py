"""A DANNCE lab run as its user would: DANNCE's `mouse_cylinder` demo (not in ../shared; in the history of
github.com/spoonsso/dannce, commit b882e8f, `demo/`): five static 1328x1048 cameras at 120 fps around a mouse in a
clear cylinder, the lab's calibration as `cam1_params.mat`...`cam5_params.mat`, and labelled frames whose 2D labels
are the 3D labels projected by DANNCE.

    python benchmarks/dannce_lab.py DEMO [--work /tmp/dannce_lab]

DEMO holds `mouse_cylinder/` (the params files and `Videos/Camera<X>/<id>/31500.mp4`) and
`mouse_cylinder_finetune/` (`cam<N>_data_applyDistort.mat`). DANNCE's config names the cameras: R = cam1, L = cam2,
E = cam3, U = cam4, S = cam5; the videos are linked as cam<N>.mp4 so that names match.
Prints: the labels' reprojection with the imported cameras (DANNCE's own projection: 0 px when the conventions are
right), each step's exit code and seconds, and the mouse's dark-blob centroid (a stand-in for a detector: found here
by a median background, not by the product) triangulated with the imported cameras, per camera median / p90
reprojection error in pixels. No 2D ground truth falls in the demo's video chunk. Last, the calibration imported
with `--synchronized` (the rig is triggered) and `dynrecon solve` of the blob (one point, whose tracks alone do not
single out the clocks): its path and its points against the blob triangulated frame by frame on the same cameras.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import scipy.io

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon
from sfm.calibration import read_calibration

CAMERAS = {"R": "cam1", "L": "cam2", "E": "cam3", "U": "cam4", "S": "cam5"}  # DANNCE's config
STEP = 4  # every 4th frame of the 120 fps videos
DARKER = 40  # grey levels under the median background: the black mouse


def _labels_px(demo: Path) -> list[tuple[str, float, float]]:
    """Per camera: median and largest distance between DANNCE's 2D labels and our projection of its 3D labels."""
    rows = []
    for camera in read_calibration(demo / "mouse_cylinder"):
        data = scipy.io.loadmat(demo / "mouse_cylinder_finetune" / f"{camera.name}_data_applyDistort.mat")
        X, uv = data["data_3d"].reshape(-1, 3) / 1000, data["data_2d"].reshape(-1, 2) - 1  # MATLAB's 1-based
        seen = np.isfinite(X).all(1) & np.isfinite(uv).all(1)
        found, _ = cv2.projectPoints(X[seen], cv2.Rodrigues(camera.R)[0], camera.t, camera.K, camera.dist)
        error = np.linalg.norm(found.reshape(-1, 2) - uv[seen], axis=1)
        rows.append((camera.name, float(np.median(error)), float(error.max())))
    return rows


def _blob_tracks(videos: list[Path], out: Path) -> None:
    """The mouse as one point: the centroid of the largest blob darker than the median background."""
    rows = []
    for video in videos:
        capture, frames, index = cv2.VideoCapture(str(video)), {}, 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if index % STEP == 0:
                frames[index] = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            index += 1
        keys = sorted(frames)
        background = np.median(np.stack([frames[k] for k in keys[:: max(1, len(keys) // 60)]]), axis=0)
        for k in keys:
            mask = ((background.astype(np.int16) - frames[k]) > DARKER).astype(np.uint8)
            mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
            count, _, stats, centres = cv2.connectedComponentsWithStats(mask)
            if count < 2:
                continue
            j = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
            if stats[j, cv2.CC_STAT_AREA] >= 300:
                rows.append((video.stem, k, "mouse", float(centres[j, 0]), float(centres[j, 1])))
    with out.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["video", "frame", "point", "x", "y"])
        writer.writerows(rows)


def _triangulated_px(cameras_dir: Path, tracks: Path) -> dict[str, tuple[float, float]]:
    """The blob centroids of frames all cameras saw, triangulated (DLT on undistorted points) and reprojected."""
    cameras = {c.name: c for c in read_calibration(cameras_dir)}
    seen: dict[int, dict[str, np.ndarray]] = {}
    for row in csv.DictReader(tracks.open()):
        seen.setdefault(int(row["frame"]), {})[row["video"]] = np.array([float(row["x"]), float(row["y"])])
    errors: dict[str, list[float]] = {name: [] for name in cameras}
    for views in seen.values():
        if len(views) < len(cameras):
            continue
        A = []
        for name, uv in views.items():
            c = cameras[name]
            x = cv2.undistortPoints(uv.reshape(1, 1, 2), c.K, c.dist).ravel()
            P = np.hstack([c.R, c.t[:, None]])
            A += [x[0] * P[2] - P[0], x[1] * P[2] - P[1]]
        X = np.linalg.svd(np.array(A))[2][-1]
        X = X[:3] / X[3]
        for name, uv in views.items():
            c = cameras[name]
            found, _ = cv2.projectPoints(X[None], cv2.Rodrigues(c.R)[0], c.t, c.K, c.dist)
            errors[name].append(float(np.linalg.norm(found.ravel() - uv)))
    return {n: (float(np.median(e)), float(np.percentile(e, 90))) for n, e in errors.items() if e}


def _run(args: list[str]) -> tuple[int, float]:
    started = time.perf_counter()
    code = dynrecon(["-q", *args])
    return code, round(time.perf_counter() - started, 1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("demo", type=Path)
    parser.add_argument("--work", type=Path, default=Path("/tmp/dannce_lab"))
    args = parser.parse_args()
    demo: Path = args.demo
    if not (demo / "mouse_cylinder" / "cam1_params.mat").exists():
        print(f"{demo}: no mouse_cylinder/cam1_params.mat: give DANNCE's demo folder")
        return 2
    shutil.rmtree(args.work, ignore_errors=True)
    videos_dir = args.work / "videos"
    videos_dir.mkdir(parents=True)
    videos = []
    for letter, name in CAMERAS.items():
        found = sorted((demo / "mouse_cylinder" / "Videos" / f"Camera{letter}").glob("*/31500.mp4"))
        (videos_dir / f"{name}.mp4").symlink_to(found[0].resolve())
        videos.append(videos_dir / f"{name}.mp4")
    paths = [str(v) for v in sorted(videos)]

    print("| camera | labels: median px | labels: largest px |")
    print("|---|---|---|")
    for name, median, largest in _labels_px(demo):
        print(f"| {name} | {median:.4f} | {largest:.4f} |")

    calibration = str(demo / "mouse_cylinder")
    steps = [
        ("register, nothing else", ["register", *paths, "--out", str(args.work / "background")]),
        ("import-calibration FOLDER", ["import-calibration", calibration, *paths, "--out", str(args.work / "cal")]),
    ]
    tracks = args.work / "mouse_tracks.csv"
    started = time.perf_counter()
    _blob_tracks(sorted(videos), tracks)
    blob_s = round(time.perf_counter() - started, 1)
    steps += [
        (
            "register --tracks (the blob)",
            ["register", *paths, "--out", str(args.work / "subject"), "--tracks", str(tracks)],
        ),
        (
            "register --tracks --intrinsics FOLDER",
            [
                "register",
                *paths,
                "--out",
                str(args.work / "subject_k"),
                "--tracks",
                str(tracks),
                "--intrinsics",
                calibration,
            ],
        ),
    ]
    synced = args.work / "synced"
    steps += [
        (
            "import-calibration FOLDER --synchronized",
            ["import-calibration", calibration, *paths, "--out", str(synced), "--synchronized"],
        ),
        (
            "solve the blob on them (one point)",
            [
                "solve",
                *("--cameras", str(synced / "cameras.json"), "--tracks", str(tracks)),
                *("--out", str(synced), "--no-recording"),
            ],
        ),
    ]
    print("\n| step | exit | s |")
    print("|---|---|---|")
    print(f"| the blob's tracks (not the product) | 0 | {blob_s} |")
    for step, command in steps:
        code, seconds = _run(command)
        print(f"| {step} | {code} | {seconds} |")

    print("\n| camera | blob triangulated with the imported cameras: median px | p90 px |")
    print("|---|---|---|")
    for name, (median, p90) in _triangulated_px(demo / "mouse_cylinder", tracks).items():
        print(f"| {name} | {median:.1f} | {p90:.1f} |")
    if (synced / "report.json").exists():
        path, (median, p90) = _solve_against_triangulation(synced, tracks)
        print(f"\nthe solve's path: {path}; its points against the synchronized triangulation of the same blob on")
        print(f"the same cameras: median {median:.1f} mm, p90 {p90:.1f} mm")
    return 0


def _solve_against_triangulation(synced: Path, tracks: Path) -> tuple[str, tuple[float, float]]:
    """report.json's temporal path, and the solve's points' distances (mm) to each observed frame triangulated with
    the other videos' observations of the same frame number (the rig is triggered)."""
    from reconstruct.inputs import build_problem_checked
    from reconstruct.outputs.points import read_points
    from reconstruct.tracks_path import start_points
    from sfm.cameras import read_cameras
    from tracking.tracks import read_tracks

    report = json.loads((synced / "report.json").read_text())
    problem, _ = build_problem_checked(read_cameras(synced / "cameras.json"), read_tracks(tracks))
    triangulated = start_points(problem, problem.times)
    solved = read_points(synced / "points3d.csv")
    index = {(v, int(f)): i for i, (v, f) in enumerate(zip(problem.frame_videos, problem.frames, strict=True))}
    rows = [index[(v, int(f))] for v, f in zip(solved.videos, solved.frames, strict=True)]
    distance = 1000 * np.linalg.norm(solved.xyz[:, 0] - triangulated[rows, 0], axis=-1)
    distance = distance[np.isfinite(distance)]
    return str(report["temporal"]["path"]), (float(np.median(distance)), float(np.percentile(distance, 90)))


if __name__ == "__main__":
    sys.exit(main())
