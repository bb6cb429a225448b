"""`register_report.json`: what `register` did, per video and per stage (see docs/formats.md)."""

from __future__ import annotations

import enum
import json
from collections.abc import Iterable
from dataclasses import is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from dynrecon.atomic import atomic_write_text
from dynrecon.jsonvalues import json_safe
from sfm.localize_frames import ADDED_KEYFRAME
from sfm.plan import FramePose, VideoPlan


def write_report(
    path: Path,
    *,
    videos: list[VideoPlan],
    results: dict[str, dict[int, FramePose]],
    timings: dict[str, float],
    warnings: list[str],
    options: Any,
    pairs: int,
    reused: list[str] | None = None,
    unreadable: dict[str, str] | None = None,
    matching: dict[str, int],
    rec: pycolmap.Reconstruction | None,
    error: str | None,
    subject: dict[str, Any] | None = None,
    background_check: dict[str, Any] | None = None,
    people: dict[str, Any] | None = None,
) -> None:
    model = None
    if rec is not None:
        model = {
            "images": int(rec.num_reg_images()),
            "points": int(rec.num_points3D()),
            "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        }
    report: dict[str, Any] = {
        "ok": error is None,
        "error": error,
        "pycolmap": pycolmap.__version__,
        "options": {
            k: (v.value if isinstance(v, enum.Enum) else str(v) if isinstance(v, Path) else v)
            for k, v in vars(options).items()
            if not is_dataclass(v)
        }
        | {
            k: {kk: (vv.value if isinstance(vv, enum.Enum) else vv) for kk, vv in vars(v).items()}
            for k, v in vars(options).items()
            if is_dataclass(v)
        },
        "model": model,
        "pairs": pairs,
        "matching": matching,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "reused_steps": list(reused or []),
        "unreadable_videos": [{"path": path, "reason": reason} for path, reason in (unreadable or {}).items()],
        "warnings": warnings,
        "videos": [_video_entry(video, results.get(video.info.name, {})) for video in videos],
        "background_check": background_check,
        "people": people,
        "subject": subject,
    }
    atomic_write_text(path, json.dumps(json_safe(report), indent=1, allow_nan=False) + "\n")  # JSON has no NaN


def _video_entry(video: VideoPlan, per_frame: dict[int, FramePose]) -> dict[str, Any]:
    posed = [r for r in per_frame.values() if r.pose is not None]
    errors = [r.error for r in posed if r.error is not None]
    failed = _failed_runs(per_frame)
    if not per_frame:
        failed = [{"first": None, "last": None, "frames": 0, "reason": "not reached (SfM stopped before localization)"}]
    sources = sorted({r.source for r in posed if r.source})
    return {
        "name": video.info.name,
        "path": str(video.info.path),
        "camera": "static" if video.static else "moving",
        "motion_test": video.motion.to_json() if video.motion is not None else None,
        "camera_set_by": "--fps" if video.info.stand_in else "--camera-motion" if video.motion_given else "motion_test",
        "posed_by": _posed_by(sources),
        "frames_in_video": video.info.num_frames,
        "frames_expected": video.info.expected_frames,
        "frames_missing": video.info.missing,
        "rotation_deg": video.info.rotation,
        "frames_given": len(video.wanted),
        "sfm_frames": len(video.sfm_frames),
        "keyframes": video.keyframes.to_json() if video.keyframes is not None else None,
        "registered": len(posed),
        "registered_by_sfm": sum(1 for r in posed if r.source == "sfm"),
        "registered_by_pnp": sum(1 for r in posed if r.source is not None and r.source.startswith(("pnp", "tracked"))),
        "registered_by_tracking": sum(1 for r in posed if r.source is not None and r.source.startswith("tracked")),
        "keyframes_added": sum(1 for r in posed if r.source == ADDED_KEYFRAME),
        "registered_by_static": sum(1 for r in posed if r.source == "static"),
        "registered_by_subject": sum(1 for r in posed if r.source == "subject"),
        "mean_reprojection_error_px": float(np.mean(errors)) if errors else None,
        "failed": failed,
        "posed": _posed_runs(per_frame),
    }


def _posed_runs(per_frame: dict[int, FramePose]) -> list[dict[str, Any]]:
    """Posed frames as runs of consecutive frame numbers posed the same way (path, inliers): a static or
    subject-posed video, whose frames share one pose, is one run; PnP frames with inliers of their own stay apart."""
    return _runs(
        (
            int(frame),
            {"path": _path(r.source), "inliers": r.inliers}
            | ({"added_keyframe": True} if r.source == ADDED_KEYFRAME else {}),
        )
        for frame, r in sorted(per_frame.items())
        if r.pose is not None
    )


def _failed_runs(per_frame: dict[int, FramePose]) -> list[dict[str, Any]]:
    """Unposed frames as runs of consecutive frame numbers that failed for the same reason: one entry per run, not
    per frame, since a failed video repeats one reason for every frame (megabytes for minutes of 120 fps video)."""
    return _runs(
        (int(frame), {"reason": r.reason or "unknown"}) for frame, r in sorted(per_frame.items()) if r.pose is None
    )


RUN_KEYS = ("first", "last", "frames")  # a run's span; its other keys are what its frames share


def _runs(entries: Iterable[tuple[int, dict[str, Any]]]) -> list[dict[str, Any]]:
    """(frame, entry) pairs in frame order as runs `{first, last, frames, **entry}` of consecutive frame numbers
    with equal entries."""
    runs: list[dict[str, Any]] = []
    for frame, entry in entries:
        if runs and runs[-1]["last"] + 1 == frame and _shared(runs[-1]) == entry:
            runs[-1]["last"] = frame
            runs[-1]["frames"] += 1
        else:
            runs.append({"first": frame, "last": frame, "frames": 1} | entry)
    return runs


def _shared(run: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in run.items() if k not in RUN_KEYS}


def posed_frames(video: dict[str, Any]) -> dict[int, dict[str, Any]]:
    """A register_report.json video entry's posed frames: frame -> its run's `path`, `inliers` (and
    `added_keyframe`)."""
    out: dict[int, dict[str, Any]] = {}
    for run in video["posed"]:
        out.update(dict.fromkeys(range(run["first"], run["last"] + 1), _shared(run)))
    return out


def _path(source: str | None) -> str:
    """How a frame was posed, in the report's words: sfm, tracked, sift (PnP of its SIFT features), static or
    subject."""
    if source == ADDED_KEYFRAME:
        return "tracked"
    return "sift" if source is not None and source.startswith("pnp") else source or "unknown"


def _posed_by(sources: list[str]) -> str:
    """The path that posed a video, in the words of the report: background SfM, PnP, static, subject or none."""
    if not sources:
        return "none"
    if "subject" in sources:
        return "subject"
    if "static" in sources:
        return "static (background SfM)"
    return "background SfM + PnP" if any(s.startswith(("pnp", "tracked")) for s in sources) else "background SfM"
