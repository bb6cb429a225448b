"""Real-video check on the Pose2Sim demo (4 static lab cameras, 60 fps): sync-free solve on desynchronized frame
subsets against triangulation from the lab calibration on synchronized frames.

    python benchmarks/pose2sim_check.py [--work /tmp/pose2sim_check] [--labels tests/data/pose2sim/labels.csv]
        [--cameras lab|subject-intrinsics|subject] [--markers] [--synchronized]

Steps (all in mm, world frame of the QCA calibration):
1. cameras: `import-calibration` of the lab's QCA file (`--scale 1000`: mm), every frame of every video posed;
   with `--cameras subject[-intrinsics]` the solve gets instead the cameras that `register --subject always` finds
   from the committed OpenPose detections (tests/data/pose2sim/openpose_tracks.csv), moved onto the lab's frame
   and mm by one similarity (their own units are arbitrary), while the reference below keeps the lab's;
   `--markers` gives `register` the labels' tracks (step 2) next to the OpenPose detections;
2. tracks: `dynrecon track` of the committed labels through every frame of each video (LK);
3. desynchronization as in the seed paper: camera k keeps frames k, k+4, k+8, ... (no two cameras share an
   instant); the solver gets only those posed frames and the tracks on them (original frame numbers and times);
4. reference: for every frame f and point, DLT + least-squares triangulation of the same tracks from every camera
   that sees the point at frame f (>= 2 cameras), with the lab calibration (synchronized frames); its
   reprojection error says how good it is;
5. distance between the sync-free point of (camera k, frame f) and the reference at frame f.

With cameras from the subject path two more numbers say where the error comes from: the same distances after one
similarity fitted on the compared points instead of on the cameras (the subject path's frame and scale are
arbitrary; centre errors of a few cm move every point through the camera similarity), and the cameras alone: the
synchronized triangulation of the same tracks with the solve's cameras against the reference, the floor any
solve on those cameras reaches. A third (`own sync`) leaves the cameras' error out: the sync-free solve against
the synchronized triangulation on its own cameras, the lab case's comparison made on the subject path's rig.

The videos are only roughly synchronized: the script also searches integer frame offsets per camera that minimize
the reference's reprojection error, and reports the comparison against that offset-corrected reference.
Needs ../shared (exits with a message otherwise). Writes WORK/comparison.csv (video, frame, point, observed,
distance_mm, distance_offset_mm: one row per compared capture).

Measured (committed labels, default solver options, frames 24..71, 186 captures, 2 contended cores: track
16-26 s, solve 12-28 s, offset search and reference 35 s):
- since the refinement's GCV skips smoothness values whose fit interpolates its rays: median 3.4 mm, p90 10.4 mm
  (tracked captures 3.3 / 9.6 mm), the same before and after a round-off change of the X-step. Before it, that
  change alone moved the result from 5.0 / 102 mm to 13.6 / 319 mm: per point, GCV picked between 1e-6 and 1e4
  from scores that were round-off (one ray per instant: small smoothness values fit every ray exactly);
- at 2aaf124: median 4.8 mm, p90 9.1 mm (tracked captures 4.8 / 8.7 mm); with --shift-clocks 4.5 / 10.4 mm;
- at 08446b9: median 14.9 mm, p90 152 mm;
- at 688e3ed: median 25.0 mm, p90 metres: 35 captures came from 6 pairs of frames of two cameras that the solver
  links with W = 1 (each the other's only neighbour, residual ~0), whose points it placed metres along their
  rays. The W = 1 pairs are still in sequencing.json at 2aaf124; the clock-based refinement fixes their points.
The reference's median reprojection error is 3.4 px. Offsets found: cam02 -1, cam03 -1, cam04 0 frames (a flat
minimum, 3.41 -> 3.24 px): the videos are synchronized to about a frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon_main
from reconstruct import stage as solve_stage
from reconstruct.outputs.points import read_points
from sfm import calibration as import_calibration
from sfm.cameras import CameraSet, FrameCamera, read_cameras, write_cameras
from sfm.evaluate import compare
from tracking import stage as track_stage
from tracking.tracks import Tracks, read_tracks, write_tracks

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
DEMO = Path("data") / "videos" / "pose2sim_demo"
LABELS = REPO / "tests" / "data" / "pose2sim" / "labels.csv"
OPENPOSE = LABELS.parent / "openpose_tracks.csv"
STRIDE = 4  # camera k keeps frames k, k+STRIDE, ...: 4 cameras, no shared instant
# Decoder times of the demo share one origin (the videos are synchronized); a sync-free solve must not profit from
# that: `--shift-clocks` adds these per-video offsets (s) to the times the solver sees, as unsynchronized phones
# would have.
CLOCK_SHIFTS = (0.0, 0.37, -0.81, 1.23)
# Frames compared: where the committed labels' tracks cover every point in most cameras (labels at 0, 32, 48;
# LK loses the fast-moving hand and feet outside this window).
WINDOW = (24, 71)


@dataclass(kw_only=True)
class CheckResult:
    points: list[str]
    # One row per compared (video, frame, point): distance (mm) between sync-free and reference.
    video: list[str] = field(default_factory=list)
    frame: list[int] = field(default_factory=list)
    point: list[str] = field(default_factory=list)
    distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # tracked in that capture
    distance_offset: np.ndarray = field(default_factory=lambda: np.zeros(0))  # against the offset-corrected ref.
    ref_error_px: dict[str, np.ndarray] = field(default_factory=dict)  # point -> per-observation reproj. error
    ref_error_offset_px: dict[str, np.ndarray] = field(default_factory=dict)
    offsets: dict[str, int] = field(default_factory=dict)  # video -> frame offset (frame f of cam01 = f + o)
    # After one similarity fitted on the compared points (the subject path's gauge is arbitrary).
    distance_similarity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # Cameras alone: synchronized triangulation with the solve's cameras vs the reference, raw and after a
    # similarity fitted on the points (empty with the lab's cameras: identical to the reference).
    floor: np.ndarray = field(default_factory=lambda: np.zeros(0))
    floor_similarity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # The solve against the synchronized triangulation with its own cameras (empty with the lab's cameras: the
    # main comparison): what the missing synchronization costs on those cameras, the camera error left out.
    own_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seconds: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------------------------
# Reference triangulation


def _project(camera: FrameCamera, X: np.ndarray) -> np.ndarray:
    """(N, 3) world -> (N, 2) pixels with distortion."""
    return _project_jacobian(camera, X)[0]


def _project_jacobian(camera: FrameCamera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world -> (N, 2) pixels with distortion, and (2N, 3): row 2i + k is d(pixel k of point i)/d(point i)."""
    uv, jac = cv2.projectPoints(
        X.reshape(-1, 3),
        cv2.Rodrigues(camera.R)[0],
        camera.t,
        camera.K,
        camera.dist if camera.dist is not None else np.zeros(4),
    )
    return uv.reshape(-1, 2), jac[:, 3:6] @ camera.R  # X enters as R X + t: d/dX = d/dt R


def triangulate(cameras: list[FrameCamera], uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """DLT on undistorted normalized rays, refined by least squares in pixels (with the projection's analytic
    Jacobian). uv: (C, 2). Returns X (3,) and the per-camera reprojection error (C,) in pixels."""
    rows = []
    for camera, p in zip(cameras, uv, strict=True):
        n = cv2.undistortPoints(
            p.reshape(1, 1, 2), camera.K, camera.dist if camera.dist is not None else np.zeros(4)
        ).reshape(2)
        P = np.c_[camera.R, camera.t]
        rows += [n[0] * P[2] - P[0], n[1] * P[2] - P[1]]
    X = np.linalg.svd(np.array(rows))[2][-1]
    X = X[:3] / X[3]

    def residual(x: np.ndarray) -> np.ndarray:
        return np.concatenate([_project(c, x)[0] - p for c, p in zip(cameras, uv, strict=True)])

    def jacobian(x: np.ndarray) -> np.ndarray:
        return np.vstack([_project_jacobian(c, x)[1] for c in cameras])

    X = least_squares(residual, X, jac=jacobian, method="lm").x
    return X, np.linalg.norm(residual(X).reshape(-1, 2), axis=1)


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (Umeyama) taking source (N, 3) onto target (N, 3): target ~ s R source + t."""
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    a, b = source - ms, target - mt
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / max(float((a**2).sum()), 1e-12))
    return s, R, mt - s * R @ ms


def similarity_distances(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N,) distances between target and source after the similarity fitted on them (N >= 3)."""
    if len(source) < 3:
        return np.full(len(source), np.nan)
    s, R, t = similarity(source, target)
    return np.linalg.norm(source @ (s * R).T + t - target, axis=1)


def _observations(tracks: Tracks) -> dict[tuple[str, int, str], np.ndarray]:
    return {
        (v, int(f), p): tracks.xy[i]
        for i, (v, f, p) in enumerate(zip(tracks.video, tracks.frame, tracks.point, strict=True))
    }


def reference(
    cameras: CameraSet,
    obs: dict[tuple[str, int, str], np.ndarray],
    points: list[str],
    offsets: dict[str, int],
    window: tuple[int, int] = WINDOW,
) -> tuple[dict[tuple[int, str], np.ndarray], dict[str, list[float]]]:
    """Triangulate every (frame f in window, point) from the cameras that see it at frame f + offset[video]
    (>= 2). Returns {(f, point): X} and point -> reprojection errors (px) of every used observation."""
    by_video = {v.name: {c.frame: c for c in v.frames} for v in cameras.videos}
    frames = sorted({f for v in cameras.videos for f in (c.frame for c in v.frames) if window[0] <= f <= window[1]})
    result: dict[tuple[int, str], np.ndarray] = {}
    errors: dict[str, list[float]] = {p: [] for p in points}
    for f in frames:
        for point in points:
            cams, uv = [], []
            for video, poses in by_video.items():
                g = f + offsets.get(video, 0)
                if (video, g, point) in obs and g in poses:
                    cams.append(poses[g])
                    uv.append(obs[(video, g, point)])
            if len(cams) < 2:
                continue
            X, err = triangulate(cams, np.array(uv))
            result[(f, point)] = X
            errors[point] += list(err)
    return result, errors


def search_offsets(
    cameras: CameraSet, obs: dict[tuple[str, int, str], np.ndarray], points: list[str], max_offset: int = 4
) -> dict[str, int]:
    """Integer frame offsets per video (the first video fixed at 0) minimizing the median reprojection error of
    the reference over points seen by >= 3 cameras; coordinate descent, two sweeps."""
    names = [v.name for v in cameras.videos]
    offsets = {n: 0 for n in names}

    def cost(candidate: dict[str, int]) -> float:
        _, errors = reference(cameras, obs, points, candidate)
        values = np.concatenate([np.asarray(e) for e in errors.values() if len(e)])
        return float(np.median(values)) if len(values) else np.inf

    for _ in range(2):
        for name in names[1:]:
            trials = {o: cost({**offsets, name: o}) for o in range(-max_offset, max_offset + 1)}
            offsets[name] = min(trials, key=lambda o: trials[o])
            log.info("offset %s: %s", name, {o: round(c, 2) for o, c in trials.items()})
    return offsets


# ---------------------------------------------------------------------------------------------------------------
# Desynchronization


def desynchronize(
    cameras: CameraSet, tracks: Tracks, stride: int = STRIDE, window: tuple[int, int] = WINDOW
) -> tuple[CameraSet, Tracks]:
    """Camera k (in file order) keeps frames k, k + stride, ... inside `window` (inclusive); tracks on dropped
    frames are dropped too. Frame numbers and times stay the videos' own."""
    keep: dict[str, set[int]] = {}
    out = CameraSet()
    for k, video in enumerate(cameras.videos):
        frames = [f for f in video.frames if f.frame % stride == k % stride and window[0] <= f.frame <= window[1]]
        keep[video.name] = {f.frame for f in frames}
        out.videos.append(dataclasses.replace(video, frames=frames))  # keeps the registered clock_offset
    rows = [i for i, (v, f) in enumerate(zip(tracks.video, tracks.frame, strict=True)) if int(f) in keep.get(v, ())]
    return out, tracks.take(rows)


# ---------------------------------------------------------------------------------------------------------------


def shift_clocks(cameras: CameraSet, shifts: tuple[float, ...] = CLOCK_SHIFTS) -> CameraSet:
    """A copy with video k's frame times + shifts[k] (frames without a time keep none); a registered clock offset
    (global = own + offset) moves by -shifts[k] so that it still names the same instants."""
    out = CameraSet()
    for k, video in enumerate(cameras.videos):
        shift = shifts[k % len(shifts)]
        frames = [dataclasses.replace(f, time=None if f.time is None else f.time + shift) for f in video.frames]
        offset = None if video.clock_offset is None else video.clock_offset - shift
        out.videos.append(dataclasses.replace(video, frames=frames, clock_offset=offset))
    return out


def subject_cameras(
    demo: Path, videos: list[Path], work: Path, lab: CameraSet, *, intrinsics: bool, markers: Path | None = None
) -> CameraSet:
    """`dynrecon register --subject always` from the committed OpenPose detections (no calibration object, no
    sync), then one similarity onto the lab's cameras: the subject path's units and frame are arbitrary, and the
    reference below is in the lab's mm frame. The similarity fixes only that gauge; every relative pose, focal and
    distortion stays as the subject path found it. `markers`: a tracks.csv whose rows join the detections."""
    ws = work / "subject"
    ws.mkdir(parents=True, exist_ok=True)
    if markers is None:
        (ws / "tracks.csv").write_bytes(OPENPOSE.read_bytes())
    else:
        write_tracks(ws / "tracks.csv", union_tracks(read_tracks(OPENPOSE), read_tracks(markers)))
    extra = ["--intrinsics", str(demo / "calibration" / "Calib.qca.txt")] if intrinsics else []
    code = dynrecon_main(["register", *(str(v) for v in videos), "--out", str(ws), "--subject", "always", *extra])
    if code != 0:
        raise SystemExit(f"register failed (exit {code}); see {ws / 'register_report.json'}")
    found = read_cameras(ws / "cameras.json")
    first = CameraSet(videos=[dataclasses.replace(v, frames=v.frames[:1]) for v in found.videos if v.frames])
    alignment = compare(first, CameraSet(videos=[dataclasses.replace(v, frames=v.frames[:1]) for v in lab.videos]))
    s, R, t = alignment.scale, alignment.rotation, alignment.translation
    out = CameraSet()
    for video in found.videos:
        frames = []
        for f in video.frames:
            R_new = f.R @ R.T  # world_lab = s R world + t  ->  cam_from_lab = R_cam R^T, centre s R c + t
            centre = s * R @ f.center + t
            frames.append(dataclasses.replace(f, R=R_new, t=-R_new @ centre))
        out.videos.append(dataclasses.replace(video, frames=frames))
    return out


def union_tracks(a: Tracks, b: Tracks) -> Tracks:
    """The rows of both (distinct point names), extra columns kept where present (empty elsewhere)."""
    names = list(dict.fromkeys([*a.extra, *b.extra]))
    return Tracks(
        video=[*a.video, *b.video],
        frame=np.concatenate([a.frame, b.frame]),
        point=[*a.point, *b.point],
        xy=np.concatenate([a.xy, b.xy]),
        extra={k: [*a.extra.get(k, [""] * len(a)), *b.extra.get(k, [""] * len(b))] for k in names},
    )


def run_check(
    shared: Path,
    work: Path,
    labels: Path = LABELS,
    *,
    search: bool = True,
    clock_shifts: bool = False,
    cameras_from: str = "lab",
    markers: bool = False,
    synchronized: bool = False,
) -> CheckResult:
    demo = shared / DEMO
    videos = sorted((demo / "videos").glob("cam*.mp4"))
    work.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    import_calibration.run(
        demo / "calibration" / "Calib.qca.txt",
        list(videos),
        work,
        import_calibration.ImportCalibrationOptions(scale=1000.0, synchronized=synchronized),
    )
    seconds["import"] = time.perf_counter() - started

    started = time.perf_counter()
    (work / "labels.csv").write_bytes(labels.read_bytes())
    track_stage.run(work, work / "tracks.csv", videos={v.stem: v for v in videos})
    seconds["track"] = time.perf_counter() - started
    if cameras_from != "lab":
        lab = read_cameras(work / "cameras.json")
        started = time.perf_counter()
        found = subject_cameras(
            demo,
            list(videos),
            work,
            lab,
            intrinsics=cameras_from == "subject-intrinsics",
            markers=work / "tracks.csv" if markers else None,
        )
        seconds["register"] = time.perf_counter() - started
        write_cameras(work / "solve_cameras.json", found)

    cameras = read_cameras(work / "cameras.json")  # the lab's: the reference triangulates with them
    tracks = read_tracks(work / "tracks.csv")
    solve_cameras = cameras if cameras_from == "lab" else read_cameras(work / "solve_cameras.json")
    desync_cameras, desync_tracks = desynchronize(solve_cameras, tracks)
    if clock_shifts:
        desync_cameras = shift_clocks(desync_cameras)
    write_cameras(work / "desync" / "cameras.json", desync_cameras)
    write_tracks(work / "desync" / "tracks.csv", desync_tracks)
    started = time.perf_counter()
    solve_stage.run(
        work / "desync" / "cameras.json",
        work / "desync" / "tracks.csv",
        work / "desync",
        solve_stage.SolveOptions(recording=None),
    )
    seconds["solve"] = time.perf_counter() - started
    solved = read_points(work / "desync" / "points3d.csv")

    started = time.perf_counter()
    points = tracks.point_names()
    obs = _observations(tracks)
    ref, ref_err = reference(cameras, obs, points, {})
    offsets = search_offsets(cameras, obs, points) if search else {v.name: 0 for v in cameras.videos}
    ref_off, ref_err_off = reference(cameras, obs, points, offsets)
    floor, floor_similarity = np.zeros(0), np.zeros(0)
    own: dict[tuple[int, str], np.ndarray] = {}
    if cameras_from != "lab":
        own, _ = reference(solve_cameras, obs, points, {})
        common = [k for k in own if k in ref]
        mine, theirs = np.array([own[k] for k in common]), np.array([ref[k] for k in common])
        floor = np.linalg.norm(mine - theirs, axis=1)
        floor_similarity = similarity_distances(mine, theirs)
    seconds["reference"] = time.perf_counter() - started

    result = CheckResult(
        points=points,
        offsets=offsets,
        seconds=seconds,
        ref_error_px={p: np.asarray(e) for p, e in ref_err.items()},
        ref_error_offset_px={p: np.asarray(e) for p, e in ref_err_off.items()},
        floor=floor,
        floor_similarity=floor_similarity,
    )
    dist, dist_off, observed, own_dist = [], [], [], []
    pairs: list[tuple[np.ndarray, np.ndarray]] = []
    for i, (video, frame) in enumerate(zip(solved.videos, solved.frames, strict=True)):
        for p, name in enumerate(solved.point_names):
            X = solved.xyz[i, p]
            key = (int(frame), name)
            if not np.all(np.isfinite(X)) or key not in ref:
                continue
            # The offset-corrected reference of this capture: cam01's clock, i.e. frame - offset[video].
            key_off = (int(frame) - offsets[video], name)
            result.video.append(video)
            result.frame.append(int(frame))
            result.point.append(name)
            observed.append(bool(solved.observed[i, p]))
            dist.append(float(np.linalg.norm(X - ref[key])))
            pairs.append((X, ref[key]))
            dist_off.append(float(np.linalg.norm(X - ref_off[key_off])) if key_off in ref_off else np.nan)
            if key in own:
                own_dist.append(float(np.linalg.norm(X - own[key])))
    result.distance = np.array(dist)
    result.own_distance = np.array(own_dist)
    result.distance_offset = np.array(dist_off)
    result.observed = np.array(observed, dtype=bool)
    result.distance_similarity = (
        similarity_distances(np.array([a for a, _ in pairs]), np.array([b for _, b in pairs])) if pairs else np.zeros(0)
    )
    _write_comparison(work / "comparison.csv", result)
    return result


def _write_comparison(path: Path, result: CheckResult) -> None:
    lines = ["video,frame,point,observed,distance_mm,distance_offset_mm"]
    for i in range(len(result.point)):
        lines.append(
            f"{result.video[i]},{result.frame[i]},{result.point[i]},{int(result.observed[i])},"
            f"{result.distance[i]:.2f},{result.distance_offset[i]:.2f}"
        )
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _stats(values: np.ndarray) -> str:
    values = values[np.isfinite(values)]
    if not len(values):
        return f"{'-':>6} {'-':>7} {0:>5}"
    return f"{np.median(values):6.1f} {np.percentile(values, 90):7.1f} {len(values):5d}"


def table(result: CheckResult) -> str:
    """Distances (mm) per point: all compared captures, the tracked ones only, and against the
    offset-corrected reference; then the reference's median reprojection error (px) without / with offsets."""
    lines = [
        f"frames {WINDOW[0]}..{WINDOW[1]}; camera k keeps frames k mod {STRIDE}; frame offsets minimizing the "
        f"reference's reprojection error (cam01 = 0): {result.offsets}",
        "",
        f"{'':10} | {'sync-free vs reference (same frame index)':^44} | {'vs offset-corrected':^24} | "
        f"{'reference':^15}",
        f"{'':10} | {'all captures':^21} | {'tracked there':^20} | {'all captures':^24} | {'reproj. px':^15}",
        f"{'point':10} | {'med':>6} {'p90':>8} {'n':>5} | {'med':>6} {'p90':>7} {'n':>5} | {'med':>6} {'p90':>8} "
        f"{'n':>8} | {'med':>6} {'offs':>7}",
    ]
    for name in [*result.points, "ALL"]:
        mask = np.ones(len(result.point), bool) if name == "ALL" else np.array([p == name for p in result.point])
        if name == "ALL":
            err = np.concatenate([e for e in result.ref_error_px.values() if len(e)] or [np.zeros(0)])
            err_off = np.concatenate([e for e in result.ref_error_offset_px.values() if len(e)] or [np.zeros(0)])
        else:
            err, err_off = result.ref_error_px.get(name, np.zeros(0)), result.ref_error_offset_px.get(name, np.zeros(0))
        med = f"{np.median(err):6.2f}" if len(err) else f"{'-':>6}"
        med_off = f"{np.median(err_off):7.2f}" if len(err_off) else f"{'-':>7}"
        tracked = result.distance[mask & result.observed]
        lines.append(
            f"{name:10} | {_stats(result.distance[mask])} | {_stats(tracked)} | "
            f"{_stats(result.distance_offset[mask])} | {med} {med_off}"
        )
    lines.append("")
    lines.append(f"{'':10} | {'med':>6} {'p90':>8} {'n':>5}")
    lines.append(
        f"{'point sim.':10} | {_stats(result.distance_similarity)} | sync-free after a similarity on the points"
    )
    if len(result.floor):
        lines.append(f"{'cameras':10} | {_stats(result.floor)} | synchronized triangulation, solve's cameras")
        lines.append(
            f"{'cam. sim.':10} | {_stats(result.floor_similarity)} | the same after a similarity on the points"
        )
        lines.append(
            f"{'own sync':10} | {_stats(result.own_distance)} | sync-free vs synchronized triangulation, both on "
            "the solve's cameras"
        )
    lines.append("")
    lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in result.seconds.items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/pose2sim_check"))
    parser.add_argument("--labels", type=Path, default=LABELS)
    parser.add_argument(
        "--shift-clocks", action="store_true", help=f"add {CLOCK_SHIFTS} s to the videos' frame times the solver sees"
    )
    parser.add_argument(
        "--cameras",
        choices=("lab", "subject-intrinsics", "subject"),
        default="lab",
        help="the solve's cameras: the lab calibration, or `register --subject always` from the committed OpenPose "
        "detections with / without the lab's intrinsics",
    )
    parser.add_argument(
        "--markers",
        action="store_true",
        help="with --cameras subject*: register from the OpenPose detections plus the labels' tracks",
    )
    parser.add_argument(
        "--synchronized",
        action="store_true",
        help="import the lab's calibration with --synchronized: the videos' clocks declared equal (the lab's rig "
        "is triggered), which the solve tests",
    )
    parser.add_argument("--shared", type=Path, default=Path(os.environ.get("DYNRECON_SHARED", REPO.parent / "shared")))
    args = parser.parse_args(argv)
    if args.synchronized and args.cameras != "lab":
        parser.error("--synchronized declares the lab calibration's clocks: use it with --cameras lab")
    logging.basicConfig(level=logging.INFO, format="%(levelname).1s %(name)s: %(message)s")
    if not (args.shared / DEMO).is_dir():
        print(f"needs {args.shared / DEMO} (the shared data folder)")
        return 1
    result = run_check(
        args.shared,
        args.work,
        args.labels,
        clock_shifts=args.shift_clocks,
        cameras_from=args.cameras,
        markers=args.markers,
        synchronized=args.synchronized,
    )
    print(table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
