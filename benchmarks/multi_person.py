"""Two participants and bystanders, raw multi-person OpenPose output, no calibration, no synchronization.

    python benchmarks/multi_person.py [--work /tmp/multi_person] [--videos DIR] [--cases NAME,...]

Data: Pose2Sim's two-participant trial (tests/data/pose2sim_multi: its raw OpenPose JSON, 2-4 people per frame in
OpenPose's own order; 4 static cameras of the lab of ../shared/data/videos/pose2sim_demo, 100 frames at 60 fps).
Its videos ship in the pose2sim wheel (`pip download --no-deps pose2sim`, Pose2Sim/Demo_MultiPerson/videos);
`--videos` takes that folder. Without it, stand-in videos of the same size, length and rate (a still picture per
camera) are written: the subject path reads only the tracks and the videos' sizes and times, and the stand-ins keep
the background path from finding anything (as on the real videos: the lab shares no usable background).

Cases (each a fresh workspace):
- `main`: `import-tracks` per camera with the default `--person 0` (people linked through the frames; the person
  seen most), then `register --subject always`;
- `all`: `--person all` (every person, numbered per video), then `register --subject always`, which matches the
  people across the videos;
- `-intrinsics` on either: with the lab's intrinsics (`--intrinsics Calib.qca.txt`);
- `dlc-all-intrinsics`: the same people as DeepLabCut multi-animal output: `all`'s linked people written per camera
  as DLC's .h5 (`to_hdf(key="df_with_missing", format="table")`, individuals `animal1`, ... in a shuffled order per
  camera), imported with `import-tracks --person all`, then as `all-intrinsics`.

Per case: the cameras against the lab's calibration after a similarity (worst centre error in % of the camera
spread, worst rotation error), register's time offsets (frames; the videos are synchronized), the people matched,
then the sync-free solve (`dynrecon solve`, defaults) of the desynchronized tracks (camera k keeps frames k, k+4,
...; no two cameras share an instant) on those cameras, against the synchronized triangulation of the same tracks
with the lab's calibration (mm, after a similarity on the points, since the cameras' frame and scale are
arbitrary; median / p90 over the compared keypoints), and the cameras alone (the synchronized triangulation with
the registered cameras: the floor of any solve on them). Needs ../shared (the lab's calibration).
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

from benchmarks.pose2sim_check import desynchronize, similarity_distances, triangulate
from benchmarks.register_real import score, truth_cameras
from dynrecon.cli import main as dynrecon
from reconstruct.outputs.points import read_points
from sfm.calibration import read_calibration
from sfm.cameras import read_cameras
from sfm.people import people_maps, renumber_people
from tracking.importing import ImportOptions, run_import
from tracking.tracks import Tracks, read_tracks, write_tracks

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data" / "pose2sim_multi" / "openpose_people.jsonl"
SHARED = REPO.parent / "shared"
CALIBRATION = SHARED / "data" / "videos" / "pose2sim_demo" / "calibration" / "Calib.qca.txt"
NAMES = [f"cam0{c}" for c in range(1, 5)]
CASES = ("main", "main-intrinsics", "all", "all-intrinsics", "dlc-all-intrinsics")
MIN_SCORE = 0.3


def openpose_folders(work: Path) -> dict[str, Path]:
    """The committed JSON lines written back as OpenPose's per-frame files; video -> its folder."""
    for line in (json.loads(text) for text in DATA.read_text().splitlines()):
        path = work / "openpose" / line["file"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"people": line["people"]}))
    return {name: work / "openpose" / f"{name}_json" for name in NAMES}


def write_dlc_h5(tracks: Tracks, folder: Path) -> dict[str, Path]:
    """Each camera's people (person<N>_<keypoint>) as a DeepLabCut multi-animal .h5, written as DLC writes it;
    individuals animal1, animal2, ... in a shuffled order per camera. Video -> its file."""
    import pandas as pd

    from tracking.people import PERSON

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(7)
    out = {}
    for name in NAMES:
        rows = [i for i, v in enumerate(tracks.video) if v == name]
        people = sorted({int(PERSON.match(tracks.point[i]).group(1)) for i in rows})  # type: ignore[union-attr]
        keypoints = sorted({PERSON.match(tracks.point[i]).group(2) for i in rows})  # type: ignore[union-attr]
        animal = {p: f"animal{k + 1}" for k, p in enumerate(rng.permutation(people))}
        columns = [(a, k, c) for a in sorted(animal.values()) for k in keypoints for c in ("x", "y", "likelihood")]
        frames = int(tracks.frame.max()) + 1
        table = np.full((frames, len(columns)), np.nan)
        where = {key: j for j, key in enumerate(columns)}
        for i in rows:
            person, keypoint = PERSON.match(tracks.point[i]).groups()  # type: ignore[union-attr]
            a = animal[int(person)]
            table[tracks.frame[i], where[a, keypoint, "x"]] = tracks.xy[i, 0]
            table[tracks.frame[i], where[a, keypoint, "y"]] = tracks.xy[i, 1]
            table[tracks.frame[i], where[a, keypoint, "likelihood"]] = float(tracks.extra["score"][i] or "nan")
        index = pd.MultiIndex.from_tuples(
            [("DLC_dlcrnetms5_demoJan1shuffle1_1000", *c) for c in columns],
            names=["scorer", "individuals", "bodyparts", "coords"],
        )
        path = folder / f"{name}DLC_dlcrnetms5_demoJan1shuffle1_1000_el.h5"
        pd.DataFrame(table, columns=index).to_hdf(path, key="df_with_missing", format="table", mode="w")
        out[name] = path
    return out


def stand_in_videos(work: Path) -> list[Path]:
    """A still picture per camera (coloured rectangles, unlike in each), 1088x1920, 100 frames at 60 fps."""
    paths = []
    for c, name in enumerate(NAMES):
        rng = np.random.default_rng(c)
        image = np.full((1920, 1088, 3), 100, np.uint8)
        for _ in range(25):
            x, y = (int(v) for v in rng.integers(0, (1000, 1800)))
            w, h = (int(v) for v in rng.integers(60, 200, 2))
            cv2.rectangle(image, (x, y), (x + w, y + h), tuple(int(v) for v in rng.integers(0, 255, 3)), -1)
        path = work / "videos" / f"{name}.mp4"
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), 60, (1088, 1920))
        for _ in range(100):
            writer.write(image)
        writer.release()
        paths.append(path)
    return paths


def lab_reference(tracks: Tracks, cameras: dict[str, Any]) -> dict[tuple[int, str], np.ndarray]:
    """(frame, point) -> the synchronized triangulation of the tracks seen by 3+ of `cameras` (video -> camera),
    where it reprojects within 30 px in every view."""
    views: dict[tuple[int, str], dict[str, np.ndarray]] = {}
    for video, frame, point, xy in zip(tracks.video, tracks.frame, tracks.point, tracks.xy, strict=True):
        if video in cameras:
            views.setdefault((int(frame), point), {})[video] = xy
    out = {}
    for key, seen in views.items():
        if len(seen) < 3:
            continue
        order = sorted(seen)
        X, error = triangulate([cameras[c] for c in order], np.array([seen[c] for c in order]))
        if error.max() < 30.0:
            out[key] = X
    return out


def run_case(case: str, work: Path, videos: list[Path]) -> dict[str, Any]:
    ws = work / case
    ws.mkdir(parents=True, exist_ok=True)
    for stale in ("cameras.json", "register_report.json", "tracks.csv"):
        (ws / stale).unlink(missing_ok=True)
    folders = openpose_folders(work)
    every = case.startswith(("all", "dlc"))
    for name, folder in folders.items():
        run_import([folder], ws / "tracks.csv", ImportOptions(video=name, min_score=MIN_SCORE, every_person=every))
    if case.startswith("dlc"):
        files = write_dlc_h5(read_tracks(ws / "tracks.csv"), ws / "dlc")
        (ws / "tracks.csv").unlink()
        for name, path in files.items():
            run_import([path], ws / "tracks.csv", ImportOptions(video=name, every_person=True))
    args = ["--subject", "always"] + (["--intrinsics", str(CALIBRATION)] if "intrinsics" in case else [])
    started = time.perf_counter()
    code = dynrecon(["register", *(str(v) for v in videos), "--out", str(ws), *args])
    row: dict[str, Any] = {"case": case, "exit": code, "register_s": round(time.perf_counter() - started, 1)}
    report = json.loads((ws / "register_report.json").read_text())
    row["posed"] = sum(v["posed_by"] == "subject" for v in report["videos"])
    row["people_s"] = report["timings_s"].get("people")
    row["people"] = (report.get("people") or {}).get("people")
    if code != 0:
        return row
    truth = truth_cameras(CALIBRATION, NAMES)
    row.update(score(read_cameras(ws / "cameras.json"), truth))
    offsets = {c["name"]: c["offset_s"] for c in (report.get("subject") or {}).get("cameras", [])}
    first = next((offsets[n] for n in NAMES if n in offsets), None)  # the synchronized videos' common offset
    row["offset_frames"] = max(abs(o - first) * 60 for o in offsets.values()) if first is not None else None
    cameras = read_cameras(ws / "cameras.json")
    tracks = renumber_people(read_tracks(ws / "tracks.csv"), people_maps(cameras))
    # camera k keeps frames k, k+4, k+8, ...: no two cameras share an instant
    write_tracks(ws / "desynchronized.csv", desynchronize(cameras, read_tracks(ws / "tracks.csv"), 4, (0, 99))[1])
    started = time.perf_counter()
    inputs = ["--cameras", str(ws / "cameras.json"), "--tracks", str(ws / "desynchronized.csv")]
    dynrecon(["solve", *inputs, "--out", str(ws / "solve"), "--no-recording"])
    row["solve_s"] = round(time.perf_counter() - started, 1)
    row["temporal_path"] = json.loads((ws / "solve" / "report.json").read_text())["temporal"]["path"]
    reference = lab_reference(tracks, {c.name: c for c in read_calibration(CALIBRATION)})
    points = read_points(ws / "solve" / "points3d.csv")
    found, true = [], []
    for i, frame in enumerate(points.frames):
        for p, point in enumerate(points.point_names):
            X = points.xyz[i, p]
            if (int(frame), point) in reference and np.isfinite(X).all():
                found.append(X)
                true.append(reference[int(frame), point])
    distances = 1000 * similarity_distances(np.array(found), np.array(true))
    row["sync_free_mm"] = (round(float(np.median(distances)), 1), round(float(np.percentile(distances, 90)), 1))
    alone = lab_reference(tracks, {v.name: v.frames[0] for v in cameras.videos if v.frames})
    keys = sorted(set(alone) & set(reference))
    floor = 1000 * similarity_distances(np.array([alone[k] for k in keys]), np.array([reference[k] for k in keys]))
    row["cameras_alone_mm"] = (round(float(np.median(floor)), 1), round(float(np.percentile(floor, 90)), 1))
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("/tmp/multi_person"))
    parser.add_argument("--videos", type=Path, help="Pose2Sim/Demo_MultiPerson/videos of the pose2sim wheel")
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args(argv)
    if not CALIBRATION.is_file():
        print(f"needs the shared data ({CALIBRATION})")
        return 1
    args.work.mkdir(parents=True, exist_ok=True)
    videos = [args.videos / f"{n}.mp4" for n in NAMES] if args.videos else stand_in_videos(args.work)
    rows = [run_case(case, args.work, videos) for case in args.cases.split(",")]
    print(f"videos: {'the trial' if args.videos else 'stand-ins'}")
    header = (
        "| case | exit | posed | centre % | rot deg | offsets (frames) | people s | register s | solve | "
        "sync-free mm | cameras alone mm |"
    )
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for r in rows:
        print(
            f"| {r['case']} | {r['exit']} | {r['posed']}/4 | {r.get('centre_pct')} | {r.get('rotation_deg')} | "
            f"{r.get('offset_frames') and round(r['offset_frames'], 2)} | {r.get('people_s')} | {r['register_s']} | "
            f"{r.get('temporal_path')} {r.get('solve_s')} s | {r.get('sync_free_mm')} | {r.get('cameras_alone_mm')} |"
        )
    for r in rows:
        if r.get("people"):
            print(f"{r['case']}: people matched (per person: video -> its own number): {r['people']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
