"""Which camera filmed which video: the solve's camera order test (reconstruct/camera_order.py) on real rigs.

    python benchmarks/camera_order.py [--work /tmp/camera_order] [--cases pose2sim-openpose,...]

Per case, the lab's own calibration is imported for the rig's videos (the right cameras), the tracks are the
committed detections or the board's corners, and then every other order of the cameras among the videos is tried
(the cameras file's poses permuted, as a calibration matched by order to videos listed wrongly would give them).
Printed: how many wrong orders were refused naming the true order, refused naming another, only warned about
(two orders fit alike), or let through with the true order found best but under the margin, or otherwise; the
right order's outcome; and the median seconds of one test.

Cases (../shared/data/videos):
- pose2sim-openpose: the 4 lab cameras (Calib.qca.txt), Pose2Sim's own OpenPose joints (tests/data/pose2sim);
- pose2sim-mediapipe: the same cameras, MediaPipe's 33 landmarks (tests/data/pose2sim);
- caliscope-corners: the 4 office webcams (camera_array.toml), the ChArUco board's corners (OpenCV's aruco);
- caliscope-mediapipe: the same cameras, MediaPipe's landmarks of the seated person (tests/data/caliscope).
"""

from __future__ import annotations

import argparse
import copy
import itertools
import logging
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon
from dynrecon.errors import InputError
from reconstruct.camera_order import check_camera_order, score_camera_order
from reconstruct.inputs import build_problem_checked
from reconstruct.stage import matched_to_videos, read_tracks
from sfm.cameras import CameraSet, read_cameras
from tracking.charuco import charuco_tracks
from tracking.tracks import write_tracks

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "videos"
DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
CASES = ("pose2sim-openpose", "pose2sim-mediapipe", "caliscope-corners", "caliscope-mediapipe")


def _workspace(case: str, work: Path) -> Path:
    """cameras.json from the lab's calibration and tracks.csv of `case`, in work/case."""
    ws = work / case
    ws.mkdir(parents=True, exist_ok=True)
    if case.startswith("pose2sim"):
        videos = [SHARED / "pose2sim_demo" / "videos" / f"cam0{i}.mp4" for i in range(1, 5)]
        calibration = SHARED / "pose2sim_demo" / "calibration" / "Calib.qca.txt"
        source = DATA / "pose2sim" / ("openpose_tracks.csv" if "openpose" in case else "mediapipe_tracks.csv")
        (ws / "tracks.csv").write_bytes(source.read_bytes())
    else:
        videos = [SHARED / "caliscope_office" / "calibration" / "extrinsic" / f"cam_{i}.mp4" for i in range(4)]
        calibration = SHARED / "caliscope_office" / "camera_array.toml"
        if "corners" in case:
            write_tracks(ws / "tracks.csv", charuco_tracks(videos, SHARED / "caliscope_office" / "charuco.toml"))
        else:
            (ws / "tracks.csv").write_bytes((DATA / "caliscope" / "mediapipe_tracks.csv").read_bytes())
    if dynrecon(["-q", "import-calibration", str(calibration), *map(str, videos), "--out", str(ws)]):
        raise SystemExit(f"{case}: import-calibration failed")
    return ws


def _permuted(cameras: CameraSet, order: tuple[int, ...]) -> CameraSet:
    """Video v given the camera of video order[v] (every frame of a static camera has the same one)."""
    moved = copy.deepcopy(cameras)
    first = [video.frames[0] for video in cameras.videos]
    for v, source in enumerate(order):
        for frame in moved.videos[v].frames:
            camera = first[source]
            frame.K, frame.R, frame.t = camera.K.copy(), camera.R.copy(), camera.t.copy()
            frame.dist = None if camera.dist is None else camera.dist.copy()
    return moved


def run_case(case: str, work: Path) -> dict[str, object]:
    ws = _workspace(case, work)
    cameras = read_cameras(ws / "cameras.json")
    names = [video.name for video in cameras.videos]
    tracks = matched_to_videos(read_tracks(ws / "tracks.csv"), names)
    counts = {"refused, true order": 0, "refused, another": 0, "warned": 0, "passed, true order best": 0, "passed": 0}
    seconds = []
    right = ""
    warned: list[logging.LogRecord] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = warned.append  # type: ignore[method-assign]
    logging.getLogger("reconstruct.camera_order").addHandler(handler)
    for order in itertools.permutations(range(len(names))):
        problem, _ = build_problem_checked(_permuted(cameras, order), tracks)
        started = time.perf_counter()
        warned.clear()
        try:
            found = check_camera_order(problem, None)
            outcome = "warned" if warned else "passed"
        except InputError:
            found = None
            outcome = "refused"
        seconds.append(time.perf_counter() - started)
        if outcome == "refused":
            scored = score_camera_order(problem)  # the order the refusal named: video v fits video order[v]'s camera
            assert scored is not None
            true = all(order[scored.order[v]] == v for v in range(len(names)))
            outcome = "refused, true order" if true else "refused, another"
        if outcome == "passed" and found is not None and all(order[found.order[v]] == v for v in range(len(names))):
            outcome = "passed, true order best" if found.swapped else outcome
        if order == tuple(range(len(names))):
            right = outcome
        else:
            counts[outcome] += 1
    wrong = len(seconds) - 1
    return {"case": case, "wrong orders": wrong, **counts, "right order": right, "s": statistics.median(seconds)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/camera_order"))
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rows = [run_case(case, args.work) for case in args.cases.split(",")]
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        print("| " + " | ".join(f"{row[k]:.1f}" if isinstance(row[k], float) else str(row[k]) for k in keys) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
