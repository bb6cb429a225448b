"""Comparing registered cameras with a reference after a similarity alignment (benchmarks and tests)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sfm.cameras import CameraSet


def _project_to_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: (s, R, t) minimizing |target - (s R source + t)|^2. source, target: (N, 3), N >= 3."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    U, S, Vt = np.linalg.svd(b.T @ a / len(source))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(axis=1).mean())
    return s, R, mu_t - s * R @ mu_s


@dataclass(kw_only=True)
class PoseComparison:
    """Per common (video, frame): centre error (reference units) and rotation error (degrees)."""

    keys: list[tuple[str, int]]
    center_errors: np.ndarray  # (N,)
    rotation_errors_deg: np.ndarray  # (N,)
    scale: float  # reference units per estimated unit
    # The alignment: x_reference = scale * rotation @ x_estimated + translation.
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    def summary(self) -> dict[str, float]:
        return {
            "frames": len(self.keys),
            "center_mean": float(self.center_errors.mean()),
            "center_max": float(self.center_errors.max()),
            "rotation_mean_deg": float(self.rotation_errors_deg.mean()),
            "rotation_max_deg": float(self.rotation_errors_deg.max()),
        }


def compare(estimated: CameraSet, reference: CameraSet) -> PoseComparison:
    """Similarity-align the estimate to the reference (rotation from orientations, scale and shift from
    centres),
    then measure every common frame."""
    keys, est, ref = [], [], []
    for video in estimated.videos:
        try:
            ref_video = reference.video(video.name)
        except KeyError:
            continue
        ref_frames = {f.frame: f for f in ref_video.frames}
        for frame in video.frames:
            if frame.frame in ref_frames:
                keys.append((video.name, frame.frame))
                est.append(frame)
                ref.append(ref_frames[frame.frame])
    if len(keys) < 3:
        raise ValueError(f"only {len(keys)} common frames; need 3 for a similarity alignment")
    est_c = np.array([f.center for f in est])
    ref_c = np.array([f.center for f in ref])
    # Rotation of the alignment from the camera orientations (chordal mean of R_ref^T R_e): centres of a few
    # cameras moving along short paths are nearly collinear and leave a rotation about that line
    # undetermined. R maps estimate to reference.
    R = _project_to_rotation(sum(r.R.T @ e.R for e, r in zip(est, ref, strict=True)))
    rotated = est_c @ R.T
    a, b = rotated - rotated.mean(axis=0), ref_c - ref_c.mean(axis=0)
    s = float((a * b).sum() / (a * a).sum())
    t = ref_c.mean(axis=0) - s * rotated.mean(axis=0)
    center_errors = np.linalg.norm(est_c @ (s * R).T + t - ref_c, axis=1)
    rotation_errors = []
    for e, r in zip(est, ref, strict=True):
        # x_cam = R_e x_est = R_e R^T (x_ref - t) / s  ->  rotation in the reference frame is R_e R^T.
        delta = e.R @ R.T @ r.R.T
        rotation_errors.append(np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1))))
    return PoseComparison(
        keys=keys,
        center_errors=center_errors,
        rotation_errors_deg=np.array(rotation_errors),
        scale=s,
        rotation=R,
        translation=t,
    )
