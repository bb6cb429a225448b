"""The background's static poses against the subject's tracks (`sfm.subject.agreement`) on the real rigs of
../shared: their own calibrations, and the same with one camera's pose made wrong, as a false background model
would make it.

    python benchmarks/background_check.py [--trials 8] [--rigs caliscope,pose2sim]

Per rig: the check of the calibration itself (the worst ratio of the poses' median epipolar distance to the
tracks' own geometry's, and whether anything was refuted), then per kind of error (a camera turned about its centre
by 2-40 degrees about a random axis; its centre moved by 20 or 50 % of its baseline in a random direction) over
`--trials` draws: how often exactly the wrong camera was refuted, how often it passed, and how often another camera
was refuted with it or instead. caliscope: the ChArUco corners (OpenCV's aruco module) with camera_array.toml;
pose2sim: Pose2Sim's OpenPose detections (tests/data/pose2sim/openpose_tracks.csv) with the lab's Calib.qca.txt.

`--plain`: the false models that pycolmap's defaults build from the office videos' backgrounds
(`register_real.plain_models`: 5 frames per video, exhaustive matching, incremental mapping), each model's static
cameras (one image stands for its video) checked with the model's own poses and intrinsics against the corners.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm.calibration import read_calibration
from sfm.subject import SubjectVideo
from sfm.subject.agreement import MAX_RATIO, MIN_PX, check_agreement
from sfm.video import probe_video
from tracking.charuco import charuco_tracks
from tracking.tracks import Tracks, read_tracks

sys.path.insert(0, str(Path(__file__).resolve().parent))
import register_real

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNRECON_SHARED", REPO.parent / "shared")) / "data" / "videos"
ROTATIONS = (2.0, 5.0, 10.0, 20.0, 40.0)
MOVES = (0.2, 0.5)


def rig(name: str, shared: Path = SHARED) -> tuple[Tracks, list[SubjectVideo]]:
    """A real rig of `shared` (../shared/data/videos) with its subject's tracks and every camera posed by the rig's
    own calibration: "caliscope" (the board's corners) or "pose2sim" (Pose2Sim's OpenPose detections)."""
    if name == "caliscope":
        root = shared / "caliscope_office"
        paths = sorted((root / "calibration" / "extrinsic").glob("cam_*.mp4"))
        calibration, tracks = root / "camera_array.toml", charuco_tracks(paths, root / "charuco.toml")
    else:
        root = shared / "pose2sim_demo"
        paths = sorted((root / "videos").glob("cam*.mp4"))
        calibration = root / "calibration" / "Calib.qca.txt"
        tracks = read_tracks(REPO / "tests" / "data" / "pose2sim" / "openpose_tracks.csv")
    cameras = {c.name: c for c in read_calibration(calibration)}
    videos = []
    for path in paths:
        info, camera = probe_video(path), cameras[path.stem]
        assert camera.R is not None and camera.t is not None
        videos.append(
            SubjectVideo(
                name=path.stem,
                width=info.width,
                height=info.height,
                times=np.asarray(info.times),
                K=camera.K,
                dist=camera.dist,
                cam_from_world=(camera.R, camera.t),
            )
        )
    return tracks, videos


def wrong(videos: list[SubjectVideo], index: int, kind: str, size: float, rng: np.random.Generator) -> list:
    video = videos[index]
    assert video.cam_from_world is not None
    R, t = video.cam_from_world
    centre = -R.T @ t
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if kind == "turn":
        R = Rotation.from_rotvec(np.radians(size) * axis).as_matrix() @ R
    else:
        others = [-v.cam_from_world[0].T @ v.cam_from_world[1] for v in videos if v is not video]  # type: ignore[index]
        baseline = float(np.median([np.linalg.norm(c - centre) for c in others]))
        centre = centre + size * baseline * axis
    moved = SubjectVideo(**{**vars(video), "cam_from_world": (R, -R @ centre)})
    return [moved if v is video else v for v in videos]


def plain(tracks: Tracks, videos: list[SubjectVideo], work: Path) -> None:
    """pycolmap's default models of the office backgrounds, checked against the corners."""
    truth = {c.name: c for c in read_calibration(SHARED / "caliscope_office" / "camera_array.toml")}
    by_name = {v.name: v for v in videos}
    print("\n| pycolmap default model | its error against camera_array.toml | pairs (poses_px / tracks_px) | refuted |")
    print("|---|---|---|---|")
    for index, model in register_real.plain_models(work).items():
        images: dict[str, Any] = {}
        for image in model.images.values():
            images.setdefault(image.name[:5], image)  # static cameras: one image stands for its video
        if len(images) < 2:
            continue
        posed = []
        for name, image in sorted(images.items()):
            camera = model.cameras[image.camera_id]
            pose = image.cam_from_world()
            K = camera.calibration_matrix()
            dist = np.array([camera.params[3], 0.0, 0.0, 0.0]) if len(camera.params) > 3 else None
            posed.append(
                SubjectVideo(
                    **{
                        **vars(by_name[name]),
                        "K": K,
                        "dist": dist,
                        "cam_from_world": (pose.rotation.matrix(), np.asarray(pose.translation)),
                    }
                )
            )
        errors = [
            register_real._pair_errors(
                a.name, b.name, images[a.name].cam_from_world(), images[b.name].cam_from_world(), truth
            )
            for n, a in enumerate(posed)
            for b in posed[n + 1 :]
        ]
        result = check_agreement(tracks, posed)
        said = ", ".join(
            f"{e['videos'][0]}-{e['videos'][1]}: {e['rotation_deg']} / {e['baseline_direction_deg']} deg"
            for e in errors
        )
        pairs = ", ".join(
            f"{p.a}-{p.b}: {p.poses_px:.1f} / {p.tracks_px:.2f}" if p.checked else f"{p.a}-{p.b}: {p.why}"
            for p in result.pairs
        )
        refuted = ", ".join(sorted(result.refuted)) or "none"
        print(
            f"| {index}: {', '.join(sorted(images))} | {said} (rotation / baseline direction) | {pairs} | {refuted} |"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--rigs", default="caliscope,pose2sim")
    parser.add_argument("--plain", action="store_true", help="also check pycolmap's default models of the office")
    parser.add_argument("--work", type=Path, default=Path("/tmp/background_check"))
    args = parser.parse_args(argv)
    if not SHARED.is_dir():
        print(f"needs the shared data folder {SHARED}")
        return 1
    rng = np.random.default_rng(0)
    print(f"limit: poses' distance > {MAX_RATIO:g} x the tracks' own (and > {MIN_PX:g} px more)\n")
    print("| rig | pose error | exactly it refuted | passed | another refuted | s per check |")
    print("|---|---|---|---|---|---|")
    for name in args.rigs.split(","):
        tracks, videos = rig(name)
        if args.plain and name == "caliscope":
            plain(tracks, videos, args.work)
        started = time.perf_counter()
        truth = check_agreement(tracks, videos)
        seconds = time.perf_counter() - started
        ratios = [p.poses_px / p.tracks_px for p in truth.pairs if p.checked and p.tracks_px and p.poses_px]
        refuted = ", ".join(sorted(truth.refuted)) or "none"
        worst = f"worst ratio {max(ratios):.2f}" if ratios else "not checked"
        print(f"| {name} | none (the calibration): {worst}, refuted: {refuted} | | | | {seconds:.1f} |")
        for kind, sizes in (("turn", ROTATIONS), ("move", MOVES)):
            for size in sizes:
                exact = passed = other = 0
                started = time.perf_counter()
                for trial in range(args.trials):
                    index = trial % len(videos)
                    result = check_agreement(tracks, wrong(videos, index, kind, size, rng))
                    names = set(result.refuted)
                    exact += names == {videos[index].name}
                    passed += not names
                    other += bool(names - {videos[index].name})
                seconds = (time.perf_counter() - started) / args.trials
                what = f"turned {size:g} deg" if kind == "turn" else f"centre moved {size:.0%} of its baseline"
                print(f"| {name} | {what} | {exact}/{args.trials} | {passed} | {other} | {seconds:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
