"""Static cameras from a moving subject (`sfm.subject`) on synthetic rigs: accuracy and time per case.

Run: python benchmarks/subject_synthetic.py
"""

from __future__ import annotations

import time

from sfm.subject import SubjectOptions, calibrate_from_subject
from sfm.subject.synthetic import compare, make_rig

CASES = {
    "skeleton P=12, 4 cams, known K": dict(kind="skeleton", n_cameras=4, noise_px=0.7),
    "skeleton P=12, 4 cams, unknown K": dict(
        kind="skeleton", n_cameras=4, noise_px=0.7, known_K=False, distortion=False
    ),
    "flight P=1, 5 cams, 1.5 px, 3% false": dict(kind="flight", n_cameras=5, noise_px=1.5, false_rate=0.03),
    "skeleton, unknown K, varied lenses": dict(kind="skeleton", n_cameras=4, noise_px=0.7, known_K=False),
    "skeleton, unknown K, identical k1=-0.115": dict(
        kind="skeleton", n_cameras=4, noise_px=0.7, known_K=False, focal=1.0, k1=-0.115
    ),
    "skeleton, unknown K, wide f=0.5w k1=-0.33": dict(
        kind="skeleton", n_cameras=4, noise_px=0.7, known_K=False, focal=0.5, k1=-0.33
    ),
    "the same, principal points 20 px off": dict(
        kind="skeleton", n_cameras=4, noise_px=0.7, known_K=False, focal=0.5, k1=-0.33, pp_sigma=20.0
    ),
}


def main() -> None:
    print(
        f"{'case':42s} {'posed':>6s} {'centre %':>9s} {'rot deg':>8s} {'offset fr':>10s} {'focal %':>8s} "
        f"{'lens':>7s} {'s':>6s}"
    )
    for name, kwargs in CASES.items():
        tracks, videos, truth = make_rig(**kwargs)  # type: ignore[arg-type]
        start = time.perf_counter()
        result = calibrate_from_subject(tracks, videos, SubjectOptions())
        seconds = time.perf_counter() - start
        e = compare(result, truth)
        print(
            f"{name:42s} {e.posed:>3d}/{len(videos):<2d} {e.centre_pct:9.3f} {e.rotation_deg:8.3f} "
            f"{e.offset_frames:10.3f} {e.focal_pct:8.2f} {result.lens.value:>7s} {seconds:6.1f}"
        )


if __name__ == "__main__":
    main()
