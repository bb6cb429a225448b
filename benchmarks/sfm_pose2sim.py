"""`register` on the real pose2sim demo (4 static lab cameras, wide baselines) against the lab's QCA
calibration.

    python benchmarks/sfm_pose2sim.py [--configs default,tuned,tuned-global] [--out /tmp/sfm_pose2sim]

For each configuration: which cameras registered, and after a similarity alignment to the QCA poses (rotation
from the orientations, scale and shift from the centres) the rotation error (deg) and the centre error (% of the
camera spread). Then, per camera pair, how many of COLMAP's verified inlier matches agree with the QCA epipolar
geometry (< 5 px): this tells whether SfM failed for lack of correct matches. Needs ../shared (skips otherwise).
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
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm import Localize, Mapper, RegisterOptions, RegistrationError, import_calibration
from sfm import register as run
from sfm.cameras import CameraSet, read_cameras
from sfm.evaluate import compare
from sfm.frames import Resize

DEMO = Path(__file__).resolve().parents[2] / "shared" / "data" / "videos" / "pose2sim_demo"
QCA = DEMO / "calibration" / "Calib.qca.txt"

CONFIGS: dict[str, dict[str, Any]] = {
    # What a new user gets: defaults, a few frames per static video.
    "default": {"max_frames": 5},
    # Best found: full resolution, many features, lab intrinsics fixed, weaker initial pair accepted.
    "tuned": {
        "max_frames": 4,
        "long_side": 1920,
        "max_features": 8192,
        "keyframes": 4,
        "init_min_inliers": 15,
        "intrinsics": QCA,
    },
    "tuned-global": {
        "max_frames": 4,
        "long_side": 1920,
        "max_features": 8192,
        "keyframes": 4,
        "init_min_inliers": 15,
        "intrinsics": QCA,
        "mapper": Mapper.GLOBAL,
    },
    "tuned-loose": {
        "max_frames": 4,
        "long_side": 1920,
        "max_features": 16384,
        "keyframes": 4,
        "init_min_inliers": 15,
        "intrinsics": QCA,
        "max_ratio": 0.85,
    },
}


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def pair_consistency(ws: Path, reference: CameraSet, long_side: int) -> dict[str, str]:
    """camera pair -> 'consistent/verified' inlier matches (epipolar distance to the QCA geometry < 5 px)."""
    out: dict[str, tuple[int, int]] = {}
    with pycolmap.Database.open(str(ws / "sfm" / "database.db")) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            va, vb = names[a].split("/")[0], names[b].split("/")[0]
            matches = np.asarray(geometry.inlier_matches)
            if va == vb or len(matches) == 0:
                continue
            fa, fb = reference.video(va).frames[0], reference.video(vb).frames[0]
            scale = Resize.for_video_size(1088, 1920, long_side).scale
            pa = np.asarray(db.read_keypoints(a))[matches[:, 0], :2] / scale - 0.5
            pb = np.asarray(db.read_keypoints(b))[matches[:, 1], :2] / scale - 0.5
            na = cv2.undistortPoints(pa[:, None], fa.K, fa.dist).reshape(-1, 2)
            nb = cv2.undistortPoints(pb[:, None], fb.K, fb.dist).reshape(-1, 2)
            R = fb.R @ fa.R.T
            E = skew(fb.t - R @ fa.t) @ R
            lines = np.c_[na, np.ones(len(na))] @ E.T
            distance = np.abs((np.c_[nb, np.ones(len(nb))] * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)
            key = "-".join(sorted((va, vb)))
            good = int((distance * fb.K[0, 0] < 5).sum())
            best = out.get(key, (0, 0))
            if (good, len(matches)) > best:
                out[key] = (good, len(matches))
    return {k: f"{g}/{n}" for k, (g, n) in sorted(out.items())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", default="default,tuned")
    parser.add_argument("--out", type=Path, default=Path("/tmp/sfm_pose2sim"))
    args = parser.parse_args()
    if not QCA.exists():
        print(f"skipped: {DEMO} not found")
        return
    videos = sorted((DEMO / "videos").glob("cam*.mp4"))
    reference = read_cameras(import_calibration(QCA, videos, args.out / "qca"))
    centers = np.array([v.frames[0].center for v in reference.videos])
    spread = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).mean())
    print(f"camera spread (mean distance to the centroid): {spread:.3f} m")
    print(
        "| config | registered cameras (frames) | rot err mean / max (deg) | centre err mean (% spread) "
        "| best verified pair inliers consistent with QCA | time (s) |"
    )
    print("|---|---|---|---|---|---|")
    for config in args.configs.split(","):
        settings = dict(CONFIGS[config])
        options = RegisterOptions(localize=Localize.NONE, **settings)
        ws = args.out / f"ws_{config}"
        started = time.perf_counter()
        try:
            path: Path | None = run(videos, ws, options)
        except RegistrationError:
            path = None
        elapsed = time.perf_counter() - started
        report = json.loads((ws / "register_report.json").read_text())
        registered = ", ".join(f"{v['name']} ({v['registered']})" for v in report["videos"] if v["registered"])
        accuracy = "n/a | n/a"
        if path is not None:
            result = compare(read_cameras(path), reference)
            accuracy = (
                f"{result.rotation_errors_deg.mean():.2f} / {result.rotation_errors_deg.max():.2f} | "
                f"{100 * result.center_errors.mean() / spread:.2f}"
            )
        pairs = pair_consistency(ws, reference, options.long_side) if (ws / "sfm" / "database.db").exists() else {}
        print(
            f"| {config} | {registered or 'none'} | {accuracy} | "
            f"{', '.join(f'{k}: {v}' for k, v in pairs.items())} | {elapsed:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
