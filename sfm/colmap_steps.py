"""The pycolmap calls of `register`, each run in a child process by `sfm.isolated.run_isolated`.

Arguments and results are plain Python values (paths as strings, dicts), so they cross the process boundary.
Never calls vocabulary-tree matching or loop detection: without a local tree file they abort the process.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Any

import pycolmap
from tqdm import tqdm

PAIRS_PER_CHUNK = 200  # match_image_pairs calls per progress-bar step


def extract(
    database: str,
    image_dir: str,
    videos: list[dict[str, Any]],
    mask_dir: str | None,
    max_features: int,
    num_threads: int,
) -> dict[str, int]:
    """SIFT features of `videos` = [{name, images, camera_model, camera_params[, max_features, wide_baseline]}],
    one pycolmap camera per video. `wide_baseline`: DSP-SIFT with affine shapes (a static video's background
    image, matched across wide baselines).

    Returns keypoints per image name.
    """
    # counted in images, not videos, so that the rate reads in images per second
    with tqdm(
        total=sum(len(v["images"]) for v in videos), desc="extracting features", unit="image", file=sys.stderr
    ) as bar:
        for video in videos:
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = video["camera_model"]
            if video["camera_params"]:
                reader.camera_params = video["camera_params"]
            if mask_dir:
                reader.mask_path = mask_dir
            options = pycolmap.FeatureExtractionOptions()
            options.sift.max_num_features = video.get("max_features", max_features)
            if video.get("wide_baseline", False):
                options.sift.estimate_affine_shape = True
                options.sift.domain_size_pooling = True
            options.num_threads = num_threads
            options.max_image_size = 100000  # frames are already resized by dynrecon
            pycolmap.extract_features(
                database,
                image_dir,
                image_names=video["images"],
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=options,
                device=pycolmap.Device.cpu,
            )
            bar.update(len(video["images"]))
    with pycolmap.Database.open(database) as db:
        return {image.name: db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()}


def extract_each(calls: list[dict[str, Any]]) -> list[dict[str, int]]:
    """`extract(**call)` for each call (one database per video) in one process; their keypoint counts."""
    return [extract(**call) for call in calls]


def match(database: str, pairs: list[tuple[str, str]], max_ratio: float, num_threads: int) -> dict[str, int]:
    """Match and verify the given image pairs; returns counts of verified pairs and inlier matches."""
    options = pycolmap.FeatureMatchingOptions()
    options.sift.max_ratio = max_ratio
    options.num_threads = num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = 0  # else each run verifies pairs differently: registration must be repeatable
    with (
        tempfile.TemporaryDirectory() as tmp,
        tqdm(total=len(pairs), desc="matching", unit="pair", file=sys.stderr) as bar,
    ):
        for start in range(0, len(pairs), PAIRS_PER_CHUNK):
            chunk = pairs[start : start + PAIRS_PER_CHUNK]
            pair_file = Path(tmp) / "pairs.txt"
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in chunk), encoding="utf-8")
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(
                database,
                matching_options=options,
                pairing_options=pairing,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
            bar.update(len(chunk))
    with pycolmap.Database.open(database) as db:
        return {
            "verified_pairs": int(db.num_verified_image_pairs()),
            "inlier_matches": int(db.num_inlier_matches()),
        }


def map_incremental(
    database: str,
    image_dir: str,
    out_dir: str,
    fix_intrinsics: bool,
    init_min_inliers: int,
    num_threads: int,
    num_images: int,
) -> dict[str, int]:
    """Incremental mapping; models go to out_dir/<index>/. Returns registered images per model index."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = 0
    options.min_model_size = 3
    options.mapper.init_min_num_inliers = init_min_inliers
    # Registering a frame needs at least as many 2D-3D inliers as a weaker initial pair had.
    options.mapper.abs_pose_min_num_inliers = min(options.mapper.abs_pose_min_num_inliers, init_min_inliers)
    if fix_intrinsics:
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
    bar = tqdm(total=num_images, desc="mapping (incremental)", unit="image", file=sys.stderr)
    try:
        models = pycolmap.incremental_mapping(
            database, image_dir, out_dir, options=options, next_image_callback=lambda: bar.update(1)
        )
    finally:
        bar.close()
    return {str(index): int(rec.num_reg_images()) for index, rec in models.items()}


def map_global(
    database: str,
    image_dir: str,
    out_dir: str,
    fix_intrinsics: bool,
    init_min_inliers: int,
    num_threads: int,
    num_images: int,
) -> dict[str, int]:
    """Global mapping (GLOMAP in pycolmap 4); models go to out_dir/<index>/."""
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = num_threads
    options.random_seed = 0
    if fix_intrinsics:
        options.mapper.bundle_adjustment.refine_focal_length = False
        options.mapper.bundle_adjustment.refine_principal_point = False
        options.mapper.bundle_adjustment.refine_extra_params = False
    with tqdm(total=1, desc=f"mapping (global, {num_images} images)", unit="run", file=sys.stderr) as bar:
        models = pycolmap.global_mapping(database, image_dir, out_dir, options=options)
        bar.update(1)
    for index, rec in models.items():
        rec.write(str(Path(out_dir) / str(index)))  # global_mapping may only keep models in memory
    return {str(index): int(rec.num_reg_images()) for index, rec in models.items()}
