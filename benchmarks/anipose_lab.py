"""An anipose lab run as its user would: sleap-anipose's test session (not in ../shared; its repository's
`tests/data/minimal_session`, e.g. from `git clone https://github.com/talmolab/sleap-anipose`).

    python benchmarks/anipose_lab.py SESSION [--work /tmp/anipose_lab]

SESSION holds `board.toml`, `calibration.toml` and per camera (back, mid, side, top) `<cam>/minimal_<cam>.mp4`,
`<cam>/minimal_<cam>_proofread.analysis.h5` and `<cam>/calibration_images/minimal_session-<cam>-calibration.MOV`.
Prints one row per step: what was posed, by which path, the seconds, and the poses against the reference: this
project's own board calibration of the calibration clips (step 2; the anipose file's `side` camera is a copy of
its `top`, so the file is compared for the other three only). Errors are the worst relative rotation between two
cameras (deg) and the worst centre after a similarity (% of the largest distance between two centres).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon
from sfm.calibration import read_calibration
from sfm.cameras import read_cameras

CAMERAS = ("back", "mid", "side", "top")
Poses = dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (R, t) cam_from_world


def _poses(ws: Path) -> Poses:
    path = ws / "cameras.json"
    if not path.exists():
        return {}
    return {v.name: (v.frames[0].R, v.frames[0].t) for v in read_cameras(path).videos if v.frames}


def _compare(found: Poses, reference: Poses) -> dict[str, Any]:
    names = [n for n in CAMERAS if n in found and n in reference]
    rotation = 0.0
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            relative = [p[b][0] @ p[a][0].T for p in (found, reference)]
            cos = (np.trace(relative[0].T @ relative[1]) - 1) / 2
            rotation = max(rotation, float(np.degrees(np.arccos(np.clip(cos, -1, 1)))))
    if len(names) < 3:
        return {"compared": names, "rotation_deg": round(rotation, 2) if len(names) == 2 else None, "centre_pct": None}
    x, y = (np.array([-p[n][0].T @ p[n][1] for n in names]) for p in (found, reference))
    xc, yc = x - x.mean(0), y - y.mean(0)
    u, s, vt = np.linalg.svd(yc.T @ xc)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    scale = float((s * np.diag(d)).sum() / (xc**2).sum())
    error = np.linalg.norm(scale * xc @ (u @ d @ vt).T - yc, axis=1)
    spread = max(float(np.linalg.norm(a - b)) for a in y for b in y)
    return {"compared": names, "rotation_deg": round(rotation, 2), "centre_pct": round(100 * error.max() / spread, 2)}


def _run(args: list[str]) -> tuple[int, float]:
    started = time.perf_counter()
    code = dynrecon(["-q", *args])
    return code, round(time.perf_counter() - started, 1)


def _solve_summary(ws: Path) -> dict[str, Any] | None:
    """Trust's flagged points, the refinement's path, and whether the solve's clocks agree with a declared one."""
    if not (ws / "report.json").exists():
        return None
    report = json.loads((ws / "report.json").read_text())
    trust, temporal = report.get("trust", {}), report.get("temporal", {})
    check = report.get("clocks", {}).get("registration_check") or {}
    return {
        "flagged": trust.get("flagged"),
        "reconstructed": trust.get("reconstructed"),
        "path": temporal.get("path"),
        "clock_claim_agrees": check.get("agree"),
    }


def _posed_by(ws: Path) -> dict[str, str]:
    path = ws / "register_report.json"
    if not path.exists():
        return {}
    return {v["name"]: v["posed_by"] for v in json.loads(path.read_text())["videos"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("session", type=Path)
    parser.add_argument("--work", type=Path, default=Path("/tmp/anipose_lab"))
    args = parser.parse_args()
    session: Path = args.session
    if not (session / "board.toml").exists():
        print(f"{session}: no board.toml: give sleap-anipose's tests/data/minimal_session")
        return 2
    shutil.rmtree(args.work, ignore_errors=True)
    clips, videos = args.work / "clips", args.work / "videos"
    clips.mkdir(parents=True)
    videos.mkdir()
    for cam in CAMERAS:  # the videos named after their cameras, as a user would name them
        (clips / f"{cam}.mov").symlink_to(
            (session / cam / "calibration_images" / f"minimal_session-{cam}-calibration.MOV").resolve()
        )
        (videos / f"{cam}.mp4").symlink_to((session / cam / f"minimal_{cam}.mp4").resolve())
    clip_paths = [str(clips / f"{cam}.mov") for cam in CAMERAS]
    video_paths = [str(videos / f"{cam}.mp4") for cam in CAMERAS]
    rows = []

    cal = args.work / "cal"
    code, seconds = _run(
        ["import-tracks", *clip_paths, "--board", str(session / "board.toml"), "--out", str(cal / "tracks.csv")]
    )
    rows.append(("1 board corners of the clips", code, seconds, {}, None))
    code, seconds = _run(["register", *clip_paths, "--out", str(cal), "--board", str(session / "board.toml")])
    reference = _poses(cal)
    anipose = {c.name: (c.R, c.t) for c in read_calibration(session / "calibration.toml") if c.name != "side"}
    rows.append(("2 register the clips --board", code, seconds, _posed_by(cal), _compare(reference, anipose)))
    markers = args.work / "cal_markers"  # nothing but the clips: register finds the board's markers itself
    code, seconds = _run(["register", *clip_paths, "--out", str(markers)])
    rows.append(
        (
            "2b register the clips (nothing else)",
            code,
            seconds,
            _posed_by(markers),
            _compare(_poses(markers), reference),
        )
    )

    def register(step: str, ws: Path) -> None:
        code, seconds = _run(["register", *video_paths, "--out", str(ws)])
        rows.append((step, code, seconds, _posed_by(ws), _compare(_poses(ws), reference)))

    def solve(step: str, ws: Path) -> None:
        tracks = args.work / "tracked" / "tracks.csv"
        code, seconds = _run(
            [
                "solve",
                "--cameras",
                str(ws / "cameras.json"),
                "--tracks",
                str(tracks),
                "--out",
                str(ws),
                "--no-recording",
            ]
        )
        rows.append((step, code, seconds, {}, _solve_summary(ws)))

    register("3 register the session (nothing else)", args.work / "background")

    tracked = args.work / "tracked"
    seconds, codes = 0.0, []
    for cam, video in zip(CAMERAS, video_paths, strict=True):
        analysis = session / cam / f"minimal_{cam}_proofread.analysis.h5"
        code, took = _run(["import-tracks", str(analysis), "--video", video, "--out", str(tracked / "tracks.csv")])
        seconds, codes = seconds + took, [*codes, code]
    rows.append(("4 import the SLEAP predictions", max(codes), round(seconds, 1), {}, None))
    register("5 register the session with the tracks", tracked)

    solved = args.work / "solved"
    code, seconds = _run(["import-calibration", str(cal / "cameras.json"), *video_paths, "--out", str(solved)])
    rows.append(("6 import-calibration cal/cameras.json", code, seconds, {}, _compare(_poses(solved), reference)))
    solve("7 solve the 15 body parts", solved)

    synced = args.work / "synced"  # the lab's cameras are triggered: the same, declared on one clock
    code, seconds = _run(
        ["import-calibration", str(cal / "cameras.json"), *video_paths, "--out", str(synced), "--synchronized"]
    )
    rows.append(("8 import-calibration --synchronized", code, seconds, {}, None))
    solve("9 solve on that clock", synced)

    print("| step | exit | s | posed by | against the reference |")
    print("|---|---|---|---|---|")
    for step, code, seconds, posed, result in rows:
        shown = ", ".join(f"{k}: {v}" for k, v in posed.items())
        print(f"| {step} | {code} | {seconds} | {shown} | {json.dumps(result) if result else ''} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
