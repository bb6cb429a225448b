"""Which features match the static background of the caliscope office webcams? Counted against the rig's calibration.

    python benchmarks/background_matching.py [--variants median,sharp-median,sharpest] [--methods sift,...]
        [--asift-scale 1.0]

Issue 16 asks `dynrecon register` to pose the 4 office webcams from their static background alone. This script
measures whether any OpenCV feature gives enough correct background matches for that, before anything is built.

Background images per video (`--variants`):
- median: what `register` sends to SfM (`sfm.per_video._write_background`): the temporal median
  (`sfm.static.background_image`) of the motion test's settled samples (all 24 samples when too few settled);
- sharp-median: the webcams refocus mid-video (the variance of the Laplacian doubles); the median of the frames
  sharper than the midpoint of the video's least and most sharp frame;
- sharpest: the single sharpest frame (the person and the board are in it).

Methods (`--methods`): sift (OpenCV defaults, Lowe ratio 0.8: the docs' baseline), rootsift (16k features, lower
contrast threshold, RootSIFT, ratio 0.8 + mutual check), colmap-dsp (COLMAP's DSP-SIFT with affine shapes, what
`register` extracts on a static background; ratio 0.8 + mutual, COLMAP's matching defaults), asift
(`cv2.AffineFeature` around SIFT at `--asift-scale`, RootSIFT, ratio + mutual), akaze (low threshold, ratio +
mutual), orb (20k features, ratio + mutual).

A match is correct when both symmetric epipolar distances (undistorted pixels, camera_array.toml's K, distortion and
poses) are under 2 px and its triangulated point lies in front of both cameras. Per pair (first table): matches
kept, correct ones, their share, how many the same points paired at random would pass (the check's floor: a few
"correct" matches are chance), the correct ones on neither image's subject pixels (the person / board in that image:
where its blurred pixels differ from the blurred median of the settled stretch, or where the subject stays in over
40 % of those frames, so that it survives in a median), their median triangulation angle, keypoints per image, CPU
(wall) seconds per image.

Second table: the 5-point relative pose (cv2.findEssentialMat, RANSAC) against the calibration's, from the correct
matches alone with the true K, and from all kept matches with the true K and with a guessed K (f = 1.2 x width,
centred, no distortion): rotation error and the baseline direction's error in degrees.

Third table: does a camera see the background that the others match? The correct background matches of the pairs
without that camera, triangulated with the calibration, and how many lie in its field of view. Fourth: the same
question without features: the share of one camera's image whose scene, were it at 1, 2 or 3 m, another sees.

Needs ../shared (exits with a message otherwise). Seconds per image are CPU seconds (all OpenCV threads).
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sfm.calibration import StaticCamera, read_calibration
from sfm.frames import Resize
from sfm.per_video import MIN_SETTLED
from sfm.static import SAMPLES, background_image, measure_motion, sample_frames
from sfm.video import ProbedVideo, probe_video, read_frames

CALISCOPE = Path(__file__).resolve().parents[2] / "shared" / "data" / "videos" / "caliscope_office"
VIDEOS = CALISCOPE / "calibration" / "extrinsic"
EPIPOLAR_PX = 2.0  # a match is correct within this distance of both epipolar lines
RATIO = 0.8
GUESSED_FOCAL = 1.2  # the guessed focal length, times the image width
MOSTLY_THERE = 0.4  # a subject that covers a pixel in this share of the frames survives in a median image
DEPTHS = (1.0, 2.0, 3.0)  # scene depths (m) of the frustum overlap: the walls are 2-3 m from the rig
FLANN_ABOVE = 12000  # float descriptors: exact brute force below this many per image, a KD-tree forest above


@dataclass
class Features:
    xy: np.ndarray  # (N, 2) pixels of the full-size image
    descriptors: np.ndarray  # (N, D) float32 or uint8
    binary: bool
    cpu_s: float
    wall_s: float


@dataclass
class View:
    name: str
    camera: StaticCamera
    images: dict[str, np.ndarray]  # variant -> BGR image at the video's size
    subject: dict[str, np.ndarray]  # variant -> (H, W) bool: the person / board in that image


# ----------------------------------------------------------------------------------------------------------
# Background images


def _sharpness(image: np.ndarray) -> float:
    return float(cv2.Laplacian(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var())


def _blurred(image: np.ndarray) -> np.ndarray:
    """Low frequencies only: refocusing changes every edge, a moving person changes whole regions."""
    return cv2.GaussianBlur(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), (0, 0), 4).astype(np.int16)


def _median(images: list[np.ndarray]) -> np.ndarray:
    return np.median(np.stack(images), axis=0).astype(np.uint8)


def load_view(info: ProbedVideo, camera: StaticCamera, variants: list[str]) -> tuple[View, str]:
    """The background images of one video and a line saying which frames made them."""
    every = dict(read_frames(info.path, np.arange(info.num_frames)))
    frames = np.array(sorted(every))
    sharp = np.array([_sharpness(every[int(f)]) for f in frames])
    motion = measure_motion(info)
    used = sample_frames(info, SAMPLES)
    if len(motion.settled) >= MIN_SETTLED:
        used = np.array(motion.settled, dtype=np.int64)
    # The subject masks from the settled stretch only: a nudged camera's early frames would mark every edge
    settled = frames[(frames >= used.min()) & (frames <= used.max())]
    background = _blurred(_median([every[int(f)] for f in settled]))
    mostly = np.mean([np.abs(_blurred(every[int(f)]) - background) > 20 for f in settled], axis=0) > MOSTLY_THERE
    images: dict[str, np.ndarray] = {}
    notes = []
    if "median" in variants:
        images["median"] = background_image(info, used, Resize.for_video(info, max(info.width, info.height)))
        notes.append(f"median of {len(used)} settled samples")
    if "sharp-median" in variants:
        cut = 0.5 * (sharp.min() + sharp.max())
        chosen = frames[sharp > cut]
        images["sharp-median"] = _median([every[int(f)] for f in chosen])
        notes.append(f"sharp-median of {len(chosen)} frames {chosen.min()}-{chosen.max()}")
    if "sharpest" in variants:
        best = int(frames[int(np.argmax(sharp))])
        images["sharpest"] = every[best]
        notes.append(f"sharpest frame {best}")
    # The subject in an image: where it differs from the background, or where the subject stays most of the time
    subject = {
        variant: cv2.dilate(((np.abs(_blurred(image) - background) > 20) | mostly).astype(np.uint8), np.ones((15, 15)))
        > 0
        for variant, image in images.items()
    }
    shares = ", ".join(f"{variant} {mask.mean():.0%}" for variant, mask in subject.items())
    line = f"{info.name}: sharpness {sharp.min():.0f}-{sharp.max():.0f}; {'; '.join(notes)}; subject pixels {shares}"
    return View(name=info.name, camera=camera, images=images, subject=subject), line


# ----------------------------------------------------------------------------------------------------------
# Features


def _root_sift(descriptors: np.ndarray) -> np.ndarray:
    """Hellinger kernel: L1-normalize, square root (Arandjelovic & Zisserman 2012)."""
    d = descriptors.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(d)


def _colmap_dsp_sift(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What `register` extracts on a static background (sfm/colmap_steps.extract, wide_baseline): COLMAP's
    DSP-SIFT with affine shapes; (N, 2) COLMAP pixels, (N, 128) float32 descriptors."""
    import warnings

    import pycolmap

    pycolmap.logging.minloglevel = 2
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = 8192
    options.sift.estimate_affine_shape = True
    options.sift.domain_size_pooling = True
    options.num_threads = 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # pycolmap.Sift still returns plain arrays
        keypoints, descriptors = pycolmap.Sift(options, pycolmap.Device.cpu).extract(np.ascontiguousarray(gray))
    return keypoints[:, :2].astype(np.float64), descriptors


def detect(method: str, image: np.ndarray, asift_scale: float) -> Features:
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    scale = asift_scale if method == "asift" else 1.0
    if scale != 1.0:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    if method == "sift":
        detector = cv2.SIFT_create()
    elif method == "rootsift":
        detector = cv2.SIFT_create(nfeatures=16000, contrastThreshold=0.02)
    elif method == "asift":
        detector = cv2.AffineFeature_create(cv2.SIFT_create(nfeatures=4000, contrastThreshold=0.02))
    elif method == "colmap-dsp":
        detector = None
    elif method == "akaze":
        # OpenCV 5 moved AKAZE to the contrib module
        akaze = getattr(cv2, "AKAZE_create", None) or cv2.xfeatures2d.AKAZE_create
        detector = akaze(threshold=0.0003)
    elif method == "orb":
        detector = cv2.ORB_create(nfeatures=20000, fastThreshold=7)
    else:
        raise ValueError(f"unknown method {method!r}")
    cpu, wall = time.process_time(), time.perf_counter()
    if detector is None:
        colmap_xy, descriptors = _colmap_dsp_sift(gray)
        xy = colmap_xy - 0.5  # COLMAP's pixel centres sit at +0.5
    else:
        keypoints, descriptors = detector.detectAndCompute(gray, None)
        xy = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    xy = (xy + 0.5) / scale - 0.5
    binary = method in ("akaze", "orb")
    if descriptors is None:
        descriptors = np.zeros((0, 32 if binary else 128), np.uint8 if binary else np.float32)
    if method in ("rootsift", "asift"):
        descriptors = _root_sift(descriptors)
    return Features(xy=xy, descriptors=descriptors, binary=binary, cpu_s=cpu, wall_s=wall)


def _knn(query: np.ndarray, train: np.ndarray, binary: bool, k: int) -> list:
    if binary:
        return cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query, train, k=k)
    if max(len(query), len(train)) <= FLANN_ABOVE:
        return cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=k)
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 128})
    return flann.knnMatch(query.astype(np.float32), train.astype(np.float32), k=k)


def match(a: Features, b: Features, mutual: bool) -> np.ndarray:
    """(M, 2) indices into a and b: Lowe's ratio test, and the mutual nearest neighbour check when asked."""
    if len(a.xy) < 2 or len(b.xy) < 2:
        return np.zeros((0, 2), np.int64)
    forward = [
        m[0]
        for m in _knn(a.descriptors, b.descriptors, a.binary, 2)
        if len(m) == 2 and m[0].distance < RATIO * m[1].distance
    ]
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in forward], dtype=np.int64).reshape(-1, 2)
    if mutual and len(pairs):
        backward = _knn(b.descriptors, a.descriptors, a.binary, 1)
        best = np.array([m[0].trainIdx if m else -1 for m in backward])
        pairs = pairs[best[pairs[:, 1]] == pairs[:, 0]]
    return pairs


# ----------------------------------------------------------------------------------------------------------
# Scoring against the calibration


def _undistorted(camera: StaticCamera, xy: np.ndarray) -> np.ndarray:
    """(N, 2) undistorted pixels (same K)."""
    if not len(xy):
        return xy
    out = cv2.undistortPoints(xy.reshape(-1, 1, 2).astype(np.float64), camera.K, camera.dist, P=camera.K)
    return out.reshape(-1, 2)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def relative(c1: StaticCamera, c2: StaticCamera) -> tuple[np.ndarray, np.ndarray]:
    """cam2_from_cam1: (R, t)."""
    R1, t1 = c1.pose()
    R2, t2 = c2.pose()
    R = R2 @ R1.T
    return R, t2 - R @ t1


def correct_matches(
    c1: StaticCamera, c2: StaticCamera, x1: np.ndarray, x2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M,) bool correct, (M,) triangulation angle in degrees, (M, 3) world points; x1, x2: (M, 2) undistorted
    pixels."""
    if not len(x1):
        return np.zeros(0, bool), np.zeros(0), np.zeros((0, 3))
    R, t = relative(c1, c2)
    F = np.linalg.inv(c2.K).T @ _skew(t) @ R @ np.linalg.inv(c1.K)
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    l2 = h1 @ F.T  # epipolar lines in image 2
    l1 = h2 @ F
    num = np.abs(np.sum(h2 * l2, axis=1))
    d2 = num / np.linalg.norm(l2[:, :2], axis=1)
    d1 = num / np.linalg.norm(l1[:, :2], axis=1)
    P1 = c1.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = c2.K @ np.hstack([R, t[:, None]])
    X = cv2.triangulatePoints(P1, P2, x1.T.astype(np.float64), x2.T.astype(np.float64))
    X = (X[:3] / X[3]).T  # in camera 1
    depth1 = X[:, 2]
    depth2 = (X @ R.T + t)[:, 2]
    centre2 = -R.T @ t
    ray1 = X / np.linalg.norm(X, axis=1, keepdims=True)
    ray2 = (X - centre2) / np.linalg.norm(X - centre2, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(ray1 * ray2, axis=1), -1, 1)))
    ok = (np.maximum(d1, d2) < EPIPOLAR_PX) & (depth1 > 0) & (depth2 > 0)
    R1, t1 = c1.pose()
    return ok, angle, (X - t1) @ R1


def chance(c1: StaticCamera, c2: StaticCamera, x1: np.ndarray, x2: np.ndarray, draws: int = 20) -> float:
    """Correct matches expected by chance: the same points paired at random (mean over `draws` shuffles)."""
    if len(x1) < 2:
        return 0.0
    rng = np.random.default_rng(0)
    return float(np.mean([correct_matches(c1, c2, x1, x2[rng.permutation(len(x2))])[0].sum() for _ in range(draws)]))


def in_view(camera: StaticCamera, points: np.ndarray) -> int:
    """How many world points (N, 3) lie inside the camera's field of view (occlusion ignored: an upper bound)."""
    if not len(points):
        return 0
    R, t = camera.pose()
    X = points @ R.T + t
    w, h = camera.width, camera.height
    border = np.array(
        [(x, y) for x in np.linspace(0, w - 1, 17) for y in (0, h - 1)]
        + [(x, y) for x in (0, w - 1) for y in np.linspace(0, h - 1, 9)]
    )
    rays = cv2.undistortPoints(border.reshape(-1, 1, 2).astype(np.float64), camera.K, camera.dist).reshape(-1, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = X[:, :2] / X[:, 2:]
    # the undistorted image is not a rectangle; its bounding box errs towards counting a point as seen
    inside = (X[:, 2] > 0) & np.all((n >= rays.min(axis=0)) & (n <= rays.max(axis=0)), axis=1)
    return int(inside.sum())


def frustum_overlap(a: StaticCamera, b: StaticCamera, depth: float) -> float:
    """Share of a's pixel grid whose rays, at `depth` along a's axis, land inside b's field of view."""
    grid = np.array([(x, y) for x in np.linspace(0, a.width - 1, 64) for y in np.linspace(0, a.height - 1, 36)])
    rays = cv2.undistortPoints(grid.reshape(-1, 1, 2).astype(np.float64), a.K, a.dist).reshape(-1, 2)
    R, t = a.pose()
    X = np.column_stack([rays, np.ones(len(rays))]) * depth
    return in_view(b, (X - t) @ R) / len(grid)


def _angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def five_point(
    p1: np.ndarray,
    p2: np.ndarray,
    K1: np.ndarray,
    K2: np.ndarray,
    threshold_px: float,
    truth: tuple[np.ndarray, np.ndarray],
) -> str:
    """'R / t deg (inliers)' of the RANSAC 5-point pose from pixels p1, p2 (N, 2), or '-' when too few."""
    if len(p1) < 8:
        return "-"
    n1 = cv2.undistortPoints(p1.reshape(-1, 1, 2).astype(np.float64), K1, None).reshape(-1, 2)
    n2 = cv2.undistortPoints(p2.reshape(-1, 1, 2).astype(np.float64), K2, None).reshape(-1, 2)
    focal = 0.5 * (K1[0, 0] + K2[0, 0])
    cv2.setRNGSeed(0)
    E, inliers = cv2.findEssentialMat(n1, n2, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=threshold_px / focal)
    if E is None or E.shape != (3, 3):
        return "fail"
    _, R, t, inliers = cv2.recoverPose(E, n1, n2, np.eye(3), mask=inliers)
    R_true, t_true = truth
    t_err = np.degrees(np.arccos(np.clip(t.ravel() @ t_true / np.linalg.norm(t_true), -1, 1)))
    return f"{_angle(R @ R_true.T):.1f} / {t_err:.0f} ({int((inliers > 0).sum())})"


# ----------------------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", default="median,sharp-median,sharpest")
    parser.add_argument("--methods", default="sift,rootsift,colmap-dsp,asift,akaze,orb")
    parser.add_argument("--asift-scale", type=float, default=1.0, help="ASIFT runs on images scaled by this")
    args = parser.parse_args()
    if not VIDEOS.is_dir():
        sys.exit(f"needs {VIDEOS} (../shared beside the repository)")
    variants = args.variants.split(",")
    methods = args.methods.split(",")
    cv2.setNumThreads(2)
    cameras = {c.name: c for c in read_calibration(CALISCOPE / "camera_array.toml")}
    views = []
    for name in sorted(cameras):
        view, line = load_view(probe_video(VIDEOS / f"{name}.mp4"), cameras[name], variants)
        print(line)
        views.append(view)
    print(f"\nASIFT at scale {args.asift_scale} (coordinates mapped back to full size); epipolar < {EPIPOLAR_PX} px")
    match_rows = []
    pose_rows = []
    best: dict[tuple[str, str, int], int] = {}  # a camera's most correct background matches with one partner
    elsewhere: dict[tuple[str, str, int], list[np.ndarray]] = {}  # background points of the pairs without camera k
    for variant in variants:
        for method in methods:
            features = [detect(method, v.images[variant], args.asift_scale) for v in views]
            cpu = np.mean([f.cpu_s for f in features])
            wall = np.mean([f.wall_s for f in features])
            counts = "/".join(str(len(f.xy)) for f in features)
            for i, j in itertools.combinations(range(len(views)), 2):
                a, b = views[i], views[j]
                pairs = match(features[i], features[j], mutual=method != "sift")
                p1 = features[i].xy[pairs[:, 0]]
                p2 = features[j].xy[pairs[:, 1]]
                u1, u2 = _undistorted(a.camera, p1), _undistorted(b.camera, p2)
                ok, angle, points = correct_matches(a.camera, b.camera, u1, u2)
                n_ok = int(ok.sum())
                background = "-"
                for k in (i, j):
                    best.setdefault((variant, method, k), 0)
                if n_ok:
                    m1, m2 = a.subject[variant], b.subject[variant]
                    r1 = np.clip(np.round(p1[ok]).astype(int), 0, [m1.shape[1] - 1, m1.shape[0] - 1])
                    r2 = np.clip(np.round(p2[ok]).astype(int), 0, [m2.shape[1] - 1, m2.shape[0] - 1])
                    hit = m1[r1[:, 1], r1[:, 0]] | m2[r2[:, 1], r2[:, 0]]
                    background = f"{int((~hit).sum())}"
                    for k in (i, j):
                        best[variant, method, k] = max(best[variant, method, k], int((~hit).sum()))
                    for k in set(range(len(views))) - {i, j}:
                        elsewhere.setdefault((variant, method, k), []).append(points[ok][~hit])
                share = f"{n_ok / len(pairs):.0%}" if len(pairs) else "-"
                tri = f"{np.median(angle[ok]):.1f}" if n_ok else "-"
                match_rows.append(
                    f"| {variant} | {method} | {a.name}-{b.name} | {len(pairs)} | {n_ok} | {share} | "
                    f"{chance(a.camera, b.camera, u1, u2):.1f} | {background} | {tri} | {counts} | "
                    f"{cpu:.1f} ({wall:.1f}) |"
                )
                truth = relative(a.camera, b.camera)
                w, h = a.camera.width, a.camera.height
                guess = np.array([[GUESSED_FOCAL * w, 0, w / 2], [0, GUESSED_FOCAL * w, h / 2], [0, 0, 1]])
                pose_rows.append(
                    f"| {variant} | {method} | {a.name}-{b.name} | "
                    f"{five_point(u1[ok], u2[ok], a.camera.K, b.camera.K, 1.0, truth)} | "
                    f"{five_point(u1, u2, a.camera.K, b.camera.K, 1.0, truth)} | "
                    f"{five_point(p1, p2, guess, guess, 3.0, truth)} |"
                )
            print(f"  {variant} {method}: {cpu:.1f} CPU s per image", flush=True)
    print(
        "\n| image | method | pair | matches | correct | share | by chance | correct on background | tri. angle (deg) "
        "| keypoints | CPU (wall) s / image |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(match_rows))
    print("\nPer camera: the most correct background matches it has with any one partner")
    print(f"\n| image | method | {' | '.join(v.name for v in views)} |")
    print(f"|---|---|{'---|' * len(views)}")
    for variant in variants:
        for method in methods:
            row = " | ".join(str(best[variant, method, k]) for k in range(len(views)))
            print(f"| {variant} | {method} | {row} |")
    print(
        "\n5-point relative pose: rotation / baseline direction error in degrees (RANSAC inliers); '-': under 8 matches"
    )
    print("\n| image | method | pair | correct only, true K | all matches, true K | all matches, guessed K |")
    print("|---|---|---|---|---|---|")
    print("\n".join(pose_rows))
    print(
        "\nOverlap: the correct background matches of the pairs without a camera, triangulated with the calibration, "
        "and how many of those points lie inside that camera's field of view (occlusion ignored)"
    )
    print("\n| image | method | camera | points from the other pairs | inside its view |")
    print("|---|---|---|---|---|")
    for (variant, method, k), chunks in sorted(
        elsewhere.items(), key=lambda item: (variants.index(item[0][0]), methods.index(item[0][1]), item[0][2])
    ):
        points = np.concatenate(chunks)
        print(f"| {variant} | {method} | {views[k].name} | {len(points)} | {in_view(views[k].camera, points)} |")
    print(
        "\nFrustum overlap (no features): the share of camera a's image whose scene, were it at depth d (m along a's "
        "axis), lies inside camera b's field of view"
    )
    print(f"\n| a | b | {' | '.join(f'd = {d:g} m' for d in DEPTHS)} |")
    print(f"|---|---|{'---|' * len(DEPTHS)}")
    for a, b in itertools.permutations(views, 2):
        print(
            f"| {a.name} | {b.name} | {' | '.join(f'{frustum_overlap(a.camera, b.camera, d):.0%}' for d in DEPTHS)} |"
        )


if __name__ == "__main__":
    main()
