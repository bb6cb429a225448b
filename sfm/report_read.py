"""What a later stage reads back from register_report.json (written by sfm/report.py; docs/formats.md)."""

from __future__ import annotations

import json
from pathlib import Path

REPORT = "register_report.json"


def unposed_videos(cameras_path: Path) -> dict[str, str]:
    """The videos that the registration report beside `cameras_path` lists without a single posed frame, each with
    the first reason it gives; empty where there is no readable report (the caller treats those names as unknown)."""
    try:
        report = json.loads((cameras_path.parent / REPORT).read_text(encoding="utf-8"))
        videos = report["videos"]
        subject_failed = (report.get("subject") or {}).get("failed") or {}
        unposed = {}
        for video in videos:
            if video.get("registered"):
                continue
            runs = video.get("failed") or [{}]
            reason = subject_failed.get(video["name"]) or runs[0].get("reason") or "no frame posed"
            unposed[str(video["name"])] = str(reason)
        return unposed
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


__all__ = ["unposed_videos"]
