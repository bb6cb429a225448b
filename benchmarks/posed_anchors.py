"""The subject path anchored by videos with known poses (`sfm.subject.posed`) on the real rigs in ../shared.

    python benchmarks/posed_anchors.py [--work /tmp/posed_anchors] [--cases NAME,...]

What `register` does when the background posed some videos (a handheld phone, say) and not the static ones: the
static videos are posed from the subject's tracks in a frame of their own, then one similarity and each posed
video's clock offset, fitted on the posed videos' tracks, move them into the background's world. Here the "posed
videos" are real videos of the rig whose poses are taken from its calibration file and handed to
`pose_from_subject` as a handheld video's would be (every frame posed, `static=False`); the other videos are
static and unposed. The tracks are the real ones (`register_real.py`'s desynchronized videos: ChArUco corners on
the office rig, OpenPose detections on the lab), the intrinsics the calibration's (`--intrinsics`).

Scored without any fitted similarity, since the posed videos set the frame and scale: the worst centre error of
the static cameras in % of the rig's camera spread (as `register_real.py`), their worst rotation error, the scale
against the truth (1 = metres), and the posed videos' clock offsets against the truth in frames.
Needs ../shared (exits with a message otherwise).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import register_real as real

from sfm.calibration import read_calibration
from sfm.frames import Resize
from sfm.options import RegisterOptions
from sfm.plan import FramePose, VideoPlan
from sfm.register_subject import pose_from_subject
from sfm.subject.synthetic import handheld, make_rig
from sfm.video import ProbedVideo, probe_video
from tracking.charuco import charuco_tracks
from tracking.tracks import Tracks, join_tracks, read_tracks, write_tracks

BLOCK_S = 0.25  # a composite "handheld" video switches between its two real cameras this often

# case -> (rig, static videos to pose, posed videos); a posed "a+b" is the composite of two real videos
CASES = {
    "caliscope-phone": ("caliscope", ("cam_1", "cam_2", "cam_3"), ("cam_0+cam_3",)),
    "pose2sim-phone": ("pose2sim", ("cam02", "cam03", "cam04"), ("cam01+cam03",)),
    "caliscope-two-posed": ("caliscope", ("cam_1", "cam_2"), ("cam_0", "cam_3")),
    "pose2sim-two-posed": ("pose2sim", ("cam02", "cam04"), ("cam01", "cam03")),
    "caliscope-one-posed": ("caliscope", ("cam_1", "cam_2", "cam_3"), ("cam_0",)),  # no scale: must be refused
}
# synthetic (sfm.subject.synthetic): 4 static cameras around a walking skeleton, a phone walking a 40 deg arc
SYNTHETIC = ("synthetic-phone", "synthetic-phone-unknown-intrinsics", "synthetic-phone-and-one-static-anchor")


def rig(name: str, work: Path) -> tuple[list[Path], Tracks, Path, dict[str, float], float]:
    """Desynchronized videos, their tracks, the calibration file, the true offsets and the frame period."""
    if name == "caliscope":
        videos = real.desynchronized_caliscope(work)
        tracks_path = work / "caliscope_corners.csv"
        if not tracks_path.exists():
            write_tracks(tracks_path, charuco_tracks(videos, real.CALISCOPE / "charuco.toml"))
        return (
            videos,
            read_tracks(tracks_path),
            real.CALISCOPE / "camera_array.toml",
            real.caliscope_true_offsets(),
            1 / 6,
        )
    videos, tracks_path = real.desynchronized_pose2sim(work)
    offsets = {n: d / 60.0 for n, d in real.DROPPED_POSE2SIM.items()}
    return videos, read_tracks(tracks_path), real.POSE2SIM / "calibration" / "Calib.qca.txt", offsets, 1 / 60


def composite(
    name: str, a: ProbedVideo, b: ProbedVideo, tracks: Tracks, offsets: dict[str, float], period: float
) -> tuple[ProbedVideo, Tracks, list[str]]:
    """A "handheld" video from two real ones: a's frames and b's frames of the same instants (by the true offsets,
    whole frames on both rigs), alternating every BLOCK_S seconds: its info, its tracks and each frame's source."""
    shift = round((offsets[a.name] - offsets[b.name]) / period)  # b's frame = composite frame + shift
    frames = min(a.num_frames, b.num_frames - shift)
    block = max(1, round(BLOCK_S / period))
    source = [a.name if (k // block) % 2 == 0 else b.name for k in range(frames)]
    rows = []
    for video, frame, point, (x, y) in zip(tracks.video, tracks.frame, tracks.point, tracks.xy, strict=True):
        k = int(frame) if video == a.name else int(frame) - shift
        if 0 <= k < frames and video == source[k]:
            rows.append((name, k, point, float(x), float(y)))
    info = ProbedVideo(
        path=Path(f"{name}.mp4"),
        name=name,
        width=a.width,
        height=a.height,
        times=a.times[:frames],
        nominal_fps=a.nominal_fps,
    )
    return info, Tracks.from_rows(rows), source


def run_synthetic(case: str) -> dict[str, object]:
    """The synthetic rig of tests/sfm/test_subject_posed.py through `pose_from_subject`; errors without similarity."""
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=4, noise_px=0.7, known_K="unknown" not in case, seed=0)
    phone = handheld(offset=0.61, arc_deg=40.0)
    plans = [_plan(_info(v.name, v.times), static=True) for v in videos] + [_plan(_info("phone", phone.times), False)]
    results: dict[str, dict[int, FramePose]] = {
        v.name: {f: FramePose(pose=None, reason="not in the background model") for f in range(len(v.times))}
        for v in videos
    }
    results["phone"] = {
        f: FramePose(
            pose=pycolmap.Rigid3d(pycolmap.Rotation3d(phone.R[f]), phone.t[f]), source="sfm", intrinsics=(phone.K, None)
        )
        for f in range(len(phone.times))
    }
    if "static-anchor" in case:
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(truth.R[0]), truth.t[0])
        results[videos[0].name] = dict.fromkeys(range(len(videos[0].times)), FramePose(pose=pose, source="sfm"))
    intrinsics = {v.name: (v.K, v.dist) for v in videos if v.K is not None}
    joined = join_tracks(tracks, phone.tracks)
    warnings: list[str] = []
    started = time.perf_counter()
    section = pose_from_subject(plans, results, joined, intrinsics, RegisterOptions(), warnings)
    row: dict[str, object] = {"case": case, "seconds": round(time.perf_counter() - started, 1), "warnings": warnings}
    if section is None or not section.get("used"):
        row["refused"] = (section or {}).get("why")
        return row
    centres = truth.centres()
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max() * 2)
    centre, rotation = {}, {}
    for i, name in enumerate(truth.names):
        pose = results[name][0].pose
        if pose is None:
            continue
        R, t = pose.rotation.matrix(), np.asarray(pose.translation)
        centre[name] = round(float(np.linalg.norm(-R.T @ t - centres[i])) / spread * 100, 3)
        cos = np.clip((np.trace(R @ truth.R[i].T) - 1) / 2, -1, 1)
        rotation[name] = round(float(np.degrees(np.arccos(cos))), 3)
    anchors = section["posed_videos"]
    found = {c["name"]: c["offset_s"] for c in section["cameras"]}
    phone_found = next(v["offset_s"] for v in anchors["videos"] if v["name"] == "phone")
    true = dict(zip(truth.names, truth.offsets, strict=True))
    row.update(
        posed=",".join(section["posed"]),
        centre_pct=centre,
        rotation_deg=rotation,
        scale_error_pct=round(100 * anchors["scale_error"], 3),
        anchor_px={v["name"]: v["residual_px"] for v in anchors["videos"]},
        offset_error_frames={
            n: round(((found[n] - phone_found) - (true[n] - phone.offset)) / truth.periods[truth.names.index(n)], 2)
            for n in found
        },
    )
    return row


def _info(name: str, times: np.ndarray) -> ProbedVideo:
    return ProbedVideo(path=Path(f"{name}.mp4"), name=name, width=1920, height=1080, times=times, nominal_fps=30.0)


def run_case(case: str, work: Path) -> dict[str, object]:
    if case in SYNTHETIC:
        return run_synthetic(case)
    rig_name, statics, posed = CASES[case]
    videos, tracks, calibration, true_offsets, period = rig(rig_name, work)
    cameras = {c.name: c for c in read_calibration(calibration)}
    infos = {v.stem: probe_video(v) for v in videos}
    plans, results, intrinsics = [], {}, {}
    subject_rows = tracks.of_videos(statics)
    all_tracks = [subject_rows]
    for name in statics:
        info = infos[name]
        plans.append(_plan(info, static=True))
        results[name] = {f: FramePose(pose=None, reason="not in the background model") for f in range(info.num_frames)}
        intrinsics[name] = (cameras[name].K, cameras[name].dist)
    for name in posed:
        if "+" in name:
            a, b = name.split("+")
            info, mine, source = composite("phone", infos[a], infos[b], tracks, true_offsets, period)
            true_offsets["phone"] = true_offsets[a]
        else:
            info, source = infos[name], [name] * infos[name].num_frames
            mine = tracks.of_videos([name])
        all_tracks.append(mine)
        plans.append(_plan(info, static=False))
        results[info.name] = {
            f: FramePose(
                pose=pycolmap.Rigid3d(pycolmap.Rotation3d(cameras[c].R), np.asarray(cameras[c].t, dtype=float)),
                source="sfm",
                intrinsics=(cameras[c].K, cameras[c].dist),
            )
            for f, c in enumerate(source)
        }
    joined = join_tracks(*all_tracks)
    warnings: list[str] = []
    started = time.perf_counter()
    section = pose_from_subject(plans, results, joined, intrinsics, RegisterOptions(), warnings)
    row: dict[str, object] = {"case": case, "seconds": round(time.perf_counter() - started, 1), "warnings": warnings}
    if section is None or not section.get("used"):
        row["refused"] = (section or {}).get("why", "; ".join(warnings))
        return row
    true_centres = {n: -c.R.T @ c.t for n, c in cameras.items()}
    all_c = np.array(list(true_centres.values()))
    spread = float(np.linalg.norm(all_c - all_c.mean(0), axis=1).max() * 2)
    centre, rotation = {}, {}
    for name in section["posed"]:
        pose = results[name][0].pose
        R, t = pose.rotation.matrix(), np.asarray(pose.translation)
        centre[name] = round(float(np.linalg.norm(-R.T @ t - true_centres[name])) / spread * 100, 2)
        cos = np.clip((np.trace(R @ cameras[name].R.T) - 1) / 2, -1, 1)
        rotation[name] = round(float(np.degrees(np.arccos(cos))), 2)
    anchors = section["posed_videos"]
    subject = {c["name"]: c["offset_s"] for c in section["cameras"]}
    # clocks against the posed video's (the anchor's)
    reference = anchors["videos"][0]["name"]
    subject[reference] = anchors["videos"][0]["offset_s"]
    offsets = {
        name: round(((found - subject[reference]) - (true_offsets[name] - true_offsets[reference])) / period, 2)
        for name, found in subject.items()
    }
    row.update(
        posed=",".join(section["posed"]),
        centre_pct=centre,
        rotation_deg=rotation,
        scale=round(anchors["scale"], 4),
        scale_error_pct=round(100 * anchors["scale_error"], 2),
        baseline=anchors["baseline"],
        anchor_px={v["name"]: v["residual_px"] for v in anchors["videos"]},
        offset_error_frames=offsets,
    )
    return row


def _plan(info: ProbedVideo, static: bool) -> VideoPlan:
    return VideoPlan(
        info=info,
        resize=Resize(scale=1.0, width=info.width, height=info.height),
        sfm_frames=np.zeros(0, dtype=np.int64),
        wanted=np.arange(info.num_frames),
        static=static,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default=",".join([*SYNTHETIC, *CASES]))
    parser.add_argument("--work", type=Path, default=Path("/tmp/posed_anchors"))
    args = parser.parse_args(argv)
    if not real.SHARED.exists():
        print(f"needs the real videos in {real.SHARED} (../shared); not found", file=sys.stderr)
        return 1
    args.work.mkdir(parents=True, exist_ok=True)
    for case in args.cases.split(","):
        print(run_case(case, args.work), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
