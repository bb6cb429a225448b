"""A DLTdv + easyWand user's files, run as that user would: bats flying past three 640x512 thermal cameras
(github.com/thejasvibr/projectushichka, commit fdd234c; not in ../shared): easyWand's `*_dltCoefs.csv` of the day
and DLTdv 7's export of 15 digitized bat tracks (`xypts`, and DLTdv's own triangulation `xyzpts` from the same
coefficients on the synchronized frames: the reference).

    python benchmarks/dltdv_real.py REPO [--work /tmp/dltdv_real]

REPO: the repository's git directory (`fetch github:thejasvibr/projectushichka`: /work/.mirror/.../repo) or a
checkout. The videos are not in the repository: stand-ins of DLTdv's row count at 640x512 and 25 fps (the
thermal cameras' rate) give import-calibration the frame count and times. Runs import-calibration,
import-tracks --pixels dltdv7 and solve, as recorded and desynchronized (0, 3 and 7 leading frames dropped), and
prints the points' distance to DLTdv's (median / p90 mm; all rows, and the rows the trust flag keeps), the
solve's `fit` and the clocks found against the frames dropped.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynrecon.cli import main as dynrecon

CALIBRATION = "acoustic-tracking/2018-08-17/speaker_playbacks/2018-08-17_wand_dltCoefs_round4.csv"
POINTS = "thermo_lidar_alignment/data/bat_trajs/DLTdv7_data_20180817-P000-15000"
FPS, SIZE = 25.0, (640, 512)
DROPPED = {"cam1": 0, "cam2": 3, "cam3": 7}


def _extract(repo: Path, path: str, out: Path) -> Path:
    """A file of the repository, from a git directory or a checkout."""
    target = out / Path(path).name
    if (repo / path).is_file():
        target.write_bytes((repo / path).read_bytes())
    else:
        target.write_bytes(
            subprocess.run(["git", "-C", str(repo), "show", f"HEAD:{path}"], check=True, capture_output=True).stdout
        )
    return target


def _video(path: Path, frames: int) -> Path:
    size = f"{SIZE[0]}x{SIZE[1]}"
    subprocess.run(
        [
            "ffmpeg",
            "-loglevel",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
            f"color=gray:s={size}:r={FPS:g}",
            "-frames:v",
            str(frames),
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            str(path),
        ],
        check=True,
    )
    return path


def _errors(result: Path, reference: np.ndarray, dropped: dict[str, int]) -> pd.DataFrame:
    points = pd.read_csv(result / "points3d.csv")
    row = points.frame + points.video.map(dropped)  # DLTdv's row (0-based) of each written point
    point = points.point.str.removeprefix("pt").astype(int) - 1
    keep = (row < len(reference)).to_numpy()
    truth = reference[row[keep].to_numpy()[:, None], 3 * point[keep].to_numpy()[:, None] + [0, 1, 2]]
    found = points.loc[keep, ["x", "y", "z"]].to_numpy()
    table = pd.DataFrame({"mm": 1000 * np.linalg.norm(found - truth, axis=1), "flag": points.flag[keep].to_numpy()})
    return table[np.isfinite(table.mm)]


def _case(
    name: str, work: Path, calibration: Path, xypts: Path, reference: np.ndarray, dropped: dict[str, int]
) -> None:
    folder = work / name
    folder.mkdir(parents=True, exist_ok=True)
    videos = [_video(folder / f"{video}.mp4", len(reference) - drop) for video, drop in dropped.items()]
    ws = folder / "ws"
    start = time.perf_counter()
    assert dynrecon(["-q", "import-calibration", str(calibration), *map(str, videos), "--out", str(ws)]) == 0
    tracks = ws / "tracks.csv"
    args = [
        "-q",
        "import-tracks",
        str(xypts),
        "--pixels",
        "dltdv7",
        "--videos",
        *map(str, videos),
        "--out",
        str(tracks),
    ]
    assert dynrecon(args) == 0
    if any(dropped.values()):  # the videos start late: each track's frames move back by the frames dropped
        table = pd.read_csv(tracks)
        table["frame"] -= table.video.map(dropped)
        table[table.frame >= 0].to_csv(tracks, index=False)
    imported = time.perf_counter() - start
    start = time.perf_counter()
    code = dynrecon(
        ["-q", "solve", "--cameras", str(ws / "cameras.json"), "--tracks", str(tracks), "--out", str(ws / "result")]
    )
    solved = time.perf_counter() - start
    report = json.loads((ws / "result" / "report.json").read_text())
    errors = _errors(ws / "result", reference, dropped)
    kept = errors[errors.flag == 0]
    offsets = {v["video"]: v.get("offset") for v in report["clocks"]["videos"]}
    frames = ", ".join(
        f"{video} {offsets[video] * FPS:+.2f} (true {drop - dropped['cam1']:+d})"
        if offsets.get(video) is not None
        else f"{video} -"
        for video, drop in dropped.items()
    )
    print(
        f"| {name} | {code} | {len(errors)} | {errors.mm.median():.1f} / {errors.mm.quantile(0.9):.1f} | "
        f"{100 * (1 - len(kept) / len(errors)):.1f} % | {kept.mm.median():.1f} / {kept.mm.quantile(0.9):.1f} | "
        f"{report['fit']['median_px']:.2f} | {frames} | {imported:.1f} + {solved:.1f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("repo", type=Path)
    parser.add_argument("--work", type=Path, default=Path("/tmp/dltdv_real"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    files = args.work / "files"
    files.mkdir(exist_ok=True)
    calibration = _extract(args.repo, CALIBRATION, files)
    xypts = _extract(args.repo, POINTS + "xypts.csv", files)
    _extract(args.repo, POINTS + "offsets.csv", files)  # DLTdv's offsets, read beside the points (all 0 here)
    reference = np.genfromtxt(_extract(args.repo, POINTS + "xyzpts.csv", files), delimiter=",", skip_header=1)
    print(
        "| case | exit | rows vs DLTdv | median / p90 mm | flagged | unflagged median / p90 mm | fit px | "
        "offsets (frames) | import + solve s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    _case("as recorded", args.work, calibration, xypts, reference, dict.fromkeys(DROPPED, 0))
    _case("desynchronized", args.work, calibration, xypts, reference, DROPPED)


if __name__ == "__main__":
    main()
