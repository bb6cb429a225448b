"""The file forms of `register`'s per-video decisions and results, so that each per-video step can run in its own
process (a Dask task) and hand its outcome to the next as a file (docs/formats.md, "Per-video registration files").

`WS/sfm/videos/<video>/plan.json`: the `VideoPlan` (the probed video, its SfM frames and wanted frames, the motion
test and keyframe choice), the SfM image names, the masks written, and the step's warnings and seconds.
`WS/sfm/videos/<video>/poses.json`: one `FramePose` per wanted frame, with the localize step's warnings and seconds.
Floats are written with Python's shortest round-trip form, so a pose read back is bit for bit the pose written.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from dynrecon.atomic import atomic_write_text
from dynrecon.errors import InputError
from sfm.frames import Resize
from sfm.keyframes import KeyframeChoice, KeyframeReason
from sfm.plan import FramePose, VideoPlan
from sfm.static import MotionTest
from sfm.video import ProbedVideo

PLAN_VERSION = 1
POSES_VERSION = 1


@dataclass(kw_only=True)
class StepNotes:
    """What a per-video step records for the capture's report: warnings, seconds per step, reused steps."""

    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)  # step -> seconds
    reused: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"warnings": self.warnings, "timings_s": self.timings, "reused_steps": self.reused}

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> StepNotes:
        return cls(
            warnings=list(document.get("warnings", [])),
            timings={str(k): float(v) for k, v in document.get("timings_s", {}).items()},
            reused=list(document.get("reused_steps", [])),
        )


@dataclass(kw_only=True)
class PreparedVideo:
    """One video after planning and writing its SfM images: `images` its SfM image names (relative to frames/),
    `masks` how many masks were written."""

    plan: VideoPlan
    images: list[str]
    masks: int
    notes: StepNotes = field(default_factory=StepNotes)


def choice_from_json(done: dict[str, Any]) -> KeyframeChoice:
    """A keyframe choice's JSON (`KeyframeChoice.to_json` plus `reasons`) back as a KeyframeChoice."""
    return KeyframeChoice(
        method=done["method"],
        frames=np.asarray(done["frames"], dtype=np.int64),
        reasons=[KeyframeReason(r) for r in done["reasons"]],
        candidates=int(done["chosen_by_content"]),
        thinned=bool(done["thinned_to_max_frames"]),
        settings={k: done[k] for k in ("motion", "survival") if k in done},  # an even choice has none
    )


def choice_to_json(choice: KeyframeChoice) -> dict[str, Any]:
    return {**choice.to_json(), "reasons": [r.value for r in choice.reasons]}


def _info_to_json(info: ProbedVideo) -> dict[str, Any]:
    return {
        "path": str(info.path),
        "name": info.name,
        "width": info.width,
        "height": info.height,
        "times": [float(t) for t in info.times],
        "nominal_fps": info.nominal_fps,
        "rotation": info.rotation,
        "expected_frames": info.expected_frames,
        "missing": info.missing,
        "stand_in": info.stand_in,
    }


def _info_from_json(d: dict[str, Any]) -> ProbedVideo:
    return ProbedVideo(
        path=Path(d["path"]),
        name=d["name"],
        width=int(d["width"]),
        height=int(d["height"]),
        times=np.asarray(d["times"], dtype=np.float64),
        nominal_fps=d["nominal_fps"],
        rotation=int(d["rotation"]),
        expected_frames=d["expected_frames"],
        missing=d["missing"],
        stand_in=bool(d.get("stand_in", False)),
    )


def _motion_to_json(motion: MotionTest) -> dict[str, Any]:
    return {
        "static": motion.static,
        "reason": motion.reason,
        "frames": [int(f) for f in motion.frames],
        "shifts": [float(s) for s in motion.shifts],
        "tracked": [float(s) for s in motion.tracked],
        "corners": motion.corners,
        "settled": [int(f) for f in motion.settled],
        "hidden": [int(f) for f in motion.hidden],
        "moved": motion.moved,
    }


def _motion_from_json(d: dict[str, Any]) -> MotionTest:
    return MotionTest(
        static=bool(d["static"]),
        reason=d["reason"],
        frames=[int(f) for f in d["frames"]],
        shifts=[float(s) for s in d["shifts"]],
        tracked=[float(s) for s in d["tracked"]],
        corners=int(d["corners"]),
        settled=[int(f) for f in d["settled"]],
        hidden=[int(f) for f in d.get("hidden", [])],
        moved=d["moved"],
    )


def write_prepared(path: Path, video: PreparedVideo) -> Path:
    plan = video.plan
    document = {
        "version": PLAN_VERSION,
        "video": _info_to_json(plan.info),
        "resize": {"scale": plan.resize.scale, "width": plan.resize.width, "height": plan.resize.height},
        "static": plan.static,
        "motion_given": plan.motion_given,
        "sfm_frames": [int(f) for f in plan.sfm_frames],
        "wanted": [int(f) for f in plan.wanted],
        "motion": _motion_to_json(plan.motion) if plan.motion is not None else None,
        "keyframes": choice_to_json(plan.keyframes) if plan.keyframes is not None else None,
        "images": video.images,
        "masks": video.masks,
        **video.notes.to_json(),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(document, indent=1) + "\n")
    return path


def read_prepared(path: Path) -> PreparedVideo:
    d = _read(path, PLAN_VERSION)
    plan = VideoPlan(
        info=_info_from_json(d["video"]),
        resize=Resize(
            scale=float(d["resize"]["scale"]), width=int(d["resize"]["width"]), height=int(d["resize"]["height"])
        ),
        sfm_frames=np.asarray(d["sfm_frames"], dtype=np.int64),
        wanted=np.asarray(d["wanted"], dtype=np.int64),
        motion=_motion_from_json(d["motion"]) if d["motion"] is not None else None,
        motion_given=bool(d.get("motion_given", False)),  # absent from the plans of earlier runs
        static=bool(d["static"]),
        keyframes=choice_from_json(d["keyframes"]) if d["keyframes"] is not None else None,
    )
    return PreparedVideo(plan=plan, images=list(d["images"]), masks=int(d["masks"]), notes=StepNotes.from_json(d))


def _resize(d: dict[str, Any]) -> Resize:
    return Resize(scale=float(d["scale"]), width=int(d["width"]), height=int(d["height"]))


def _pose_to_json(frame: int, pose: FramePose) -> dict[str, Any]:
    entry: dict[str, Any] = {"frame": frame, "source": pose.source, "reason": pose.reason}
    if pose.pose is not None:
        entry["quat_xyzw"] = [float(v) for v in np.asarray(pose.pose.rotation.quat)]
        entry["t"] = [float(v) for v in np.asarray(pose.pose.translation)]
    if pose.intrinsics is not None:
        K, dist = pose.intrinsics
        entry["K"] = np.asarray(K, dtype=np.float64).tolist()
        entry["dist"] = None if dist is None else np.asarray(dist, dtype=np.float64).tolist()
    entry["error"] = pose.error
    entry["inliers"] = pose.inliers
    return entry


def _pose_from_json(d: dict[str, Any]) -> FramePose:
    pose = None
    if "quat_xyzw" in d:
        rotation = pycolmap.Rotation3d(np.asarray(d["quat_xyzw"], dtype=np.float64))
        pose = pycolmap.Rigid3d(rotation, np.asarray(d["t"], dtype=np.float64))
    intrinsics = None
    if "K" in d:
        dist = None if d["dist"] is None else np.asarray(d["dist"], dtype=np.float64)
        intrinsics = (np.asarray(d["K"], dtype=np.float64), dist)
    return FramePose(
        pose=pose,
        reason=d["reason"],
        source=d["source"],
        error=d["error"],
        intrinsics=intrinsics,
        inliers=d["inliers"],
    )


def write_poses(path: Path, video: str, poses: dict[int, FramePose], notes: StepNotes) -> Path:
    """poses: frame -> FramePose of every wanted frame of `video`, kept in its order."""
    document = {
        "version": POSES_VERSION,
        "video": video,
        "frames": [_pose_to_json(int(f), p) for f, p in poses.items()],  # in their order: the report averages them
        **notes.to_json(),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(document, indent=1) + "\n")
    return path


def read_poses(path: Path) -> tuple[dict[int, FramePose], StepNotes]:
    d = _read(path, POSES_VERSION)
    return {int(e["frame"]): _pose_from_json(e) for e in d["frames"]}, StepNotes.from_json(d)


def _read(path: Path, version: int) -> dict[str, Any]:
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise InputError(path, f"cannot read this per-video registration file: {error}") from None
    if not isinstance(document, dict) or document.get("version") != version:
        raise InputError(path, f"not a version {version} per-video registration file", fix="register again")
    return document
