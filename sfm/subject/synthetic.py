"""Synthetic static rigs with ground truth: cameras, unsynchronized videos, a moving subject, noisy 2D tracks."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from sfm.subject.model import SubjectResult, SubjectVideo
from tracking.tracks import Tracks


@dataclass(kw_only=True)
class Truth:
    names: list[str]
    K: list[np.ndarray]  # (3, 3) each
    dist: list[np.ndarray | None]
    R: list[np.ndarray]  # (3, 3) cam_from_world
    t: list[np.ndarray]  # (3,)
    offsets: list[float]  # global = own + offset, video 0 at 0
    periods: list[float]  # frame period of each video (s)
    point_names: list[str]

    def centres(self) -> np.ndarray:
        return np.array([-R.T @ t for R, t in zip(self.R, self.t, strict=True)])  # (V, 3)


def _look_at(centre: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])  # world z is up; camera y points down
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ centre


def skeleton_motion(t: np.ndarray, n_points: int = 12) -> np.ndarray:
    """(T,) global seconds -> (T, P, 3): a body-like cloud walking a curved path in a ~4 m room, limbs swinging."""
    return _walker(t, n_points, path=(0.31, 0.23, 1.7, 0.7), limbs=(0.9, 0.7), seed=7)


def other_walker(t: np.ndarray, n_points: int = 12) -> np.ndarray:
    """(T,) -> (T, P, 3): another person in `skeleton_motion`'s room: another body, path and pace."""
    return _walker(t, n_points, path=(0.43, 0.17, 1.3, 2.1), limbs=(1.3, 0.55), seed=11)


def _walker(
    t: np.ndarray, n_points: int, path: tuple[float, float, float, float], limbs: tuple[float, float], seed: int
) -> np.ndarray:
    """A body of `n_points` on a curved walk (`path`: the x, y and bounce frequencies and the y phase), limbs
    swinging at `limbs` Hz."""
    rng = np.random.default_rng(seed)
    body = np.column_stack(
        [rng.uniform(-0.25, 0.25, n_points), rng.uniform(-0.15, 0.15, n_points), np.linspace(0.05, 1.8, n_points)]
    )  # (P, 3) body frame, z up
    fx, fy, fz, phase = path
    centre = np.column_stack([1.5 * np.sin(fx * t), 1.2 * np.sin(fy * t + phase), 0.1 * np.sin(fz * t)])
    heading = fx * t + 0.6 * np.sin(0.5 * t)
    c, s = np.cos(heading), np.sin(heading)
    swing = 0.25 * np.sin(2 * np.pi * limbs[0] * t[:, None] + np.arange(n_points)[None, :])  # (T, P) limb motion
    bx = body[None, :, 0] + swing * (body[None, :, 2] < 1.0)
    by = body[None, :, 1] + 0.1 * np.cos(2 * np.pi * limbs[1] * t[:, None] + 2 * np.arange(n_points)[None, :])
    bz = body[None, :, 2] + 0.05 * swing
    x = c[:, None] * bx - s[:, None] * by + centre[:, None, 0]
    y = s[:, None] * bx + c[:, None] * by + centre[:, None, 1]
    return np.stack([x, y, bz + centre[:, None, 2]], axis=-1)


def flight_motion(t: np.ndarray) -> np.ndarray:
    """(T,) -> (T, 1, 3): a drone/ball on a curved non-planar path, ~10 m/s, within ~40 m of the origin."""
    x = 25.0 * np.sin(0.3 * t)
    y = 18.0 * np.sin(0.42 * t + 1.0)
    z = 15.0 + 6.0 * np.sin(0.55 * t + 0.3) + 3.0 * np.cos(0.9 * t)
    return np.stack([x, y, z], axis=-1)[:, None, :]


def line_motion(t: np.ndarray) -> np.ndarray:
    """(T,) -> (T, 1, 3): back and forth along one 3D line (degenerate for self-calibration)."""
    s = 15.0 * np.sin(0.4 * t)
    return (np.array([5.0, 2.0, 12.0]) + s[:, None] * np.array([0.8, 0.5, 0.33]))[:, None, :]


def sway_motion(t: np.ndarray) -> np.ndarray:
    """(T,) -> (T, 5, 3): five markers of someone balancing on the spot (centimetres of motion: few positions)."""
    base = np.array([[0.1, 0.0, 0.05], [0.1, 0.05, 0.1], [0.05, 0.05, 0.5], [0.3, -0.1, 1.0], [-0.1, 0.0, 0.05]])
    sway = 0.01 * np.stack([np.sin(0.7 * t), np.cos(0.5 * t), 0.3 * np.sin(1.1 * t)], axis=-1)  # (T, 3)
    return base[None] + sway[:, None] * (1 + base[None, :, 2:3])


def make_rig(
    *,
    kind: str = "skeleton",  # "skeleton", "flight", "line" or "sway"
    n_cameras: int = 4,
    duration: float = 20.0,
    fps: tuple[float, ...] = (30.0, 25.0, 60.0, 29.97, 30.0),
    offsets: tuple[float, ...] = (0.0, 1.37, -2.21, 0.83, -0.52),
    noise_px: float = 0.7,
    bias_px: float = 0.0,
    drop: float = 0.05,
    false_rate: float = 0.0,
    known_K: bool = True,
    distortion: bool = True,
    focal: float | None = None,
    k1: float | None = None,
    pp_sigma: float = 5.0,
    seed: int = 0,
    motion: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[Tracks, list[SubjectVideo], Truth]:
    """Cameras around the scene, looking at its middle; video v's own clock starts at global time offsets[v].

    `focal` (in units of the image width) and `k1` (with k2 = 0.01) make every camera the same lens (identical
    webcams; a wide-angle one with a small focal and a strong k1); `pp_sigma`: pixels of principal point scatter;
    `bias_px`: scatter of a constant shift per camera and point, as a pose detector's keypoint (a joint's centre
    seen from another side) has on top of its `noise_px`; `motion` replaces the kind's subject (the same cameras:
    another person in the same room)."""
    rng = np.random.default_rng(seed)
    if kind in ("skeleton", "sway"):
        default = skeleton_motion if kind == "skeleton" else sway_motion
        target, radius, height = np.array([0.0, 0.0, 1.0]), 5.0, 2.6
        width, hgt = 1920, 1080
    else:
        default = flight_motion if kind == "flight" else line_motion
        target, radius, height = np.array([0.0, 0.0, 12.0]), 60.0, 1.7
        width, hgt = 1920, 1080
    motion = motion or default
    names, Ks, dists, Rs, ts, periods = [], [], [], [], [], []
    rows: list[tuple[str, int, str, float, float]] = []
    videos: list[SubjectVideo] = []
    n_points = motion(np.zeros(1)).shape[1]
    point_names = [f"p{i}" for i in range(n_points)] if n_points > 1 else ["ball"]
    for v in range(n_cameras):
        angle = 2 * np.pi * v / n_cameras + rng.uniform(-0.15, 0.15)
        r = radius * (rng.uniform(0.55, 1.6) if kind in ("flight", "line") else rng.uniform(0.9, 1.1))
        centre = np.array([r * np.cos(angle), r * np.sin(angle), height + rng.uniform(-0.3, 0.5)])
        R, t = _look_at(centre, target + rng.normal(0, 3.0 if kind in ("flight", "line") else 0.3, 3))
        # the flight fits in every view: wider lenses for the nearer cameras
        f = rng.uniform(0.85, 1.1) * width * (min(1.0, r / 110) if kind in ("flight", "line") else 1.0)
        f = f if focal is None else focal * width
        pp = rng.normal(0, 1, 2) * pp_sigma
        K = np.array([[f, 0, width / 2 + pp[0]], [0, f, hgt / 2 + pp[1]], [0, 0, 1.0]])
        lens_k1 = rng.uniform(-0.12, 0.05) if k1 is None else k1
        dist = np.array([lens_k1, 0.01, 0.0, 0.0, 0.0]) if distortion else None
        period = 1.0 / fps[v % len(fps)]
        offset = offsets[v % len(offsets)] if v else 0.0
        own = np.arange(0.0, duration - max(offset, 0.0), period)  # own clock from 0; global = own + offset
        X = motion(own + offset)  # (F, P, 3)
        Xc = X @ R.T + t
        uv, _ = cv2.projectPoints(X.reshape(-1, 3), cv2.Rodrigues(R)[0], t, K, dist)
        uv = uv.reshape(len(own), n_points, 2) + rng.normal(0, noise_px, (len(own), n_points, 2))
        if bias_px:
            uv += rng.normal(0, bias_px, (1, n_points, 2))
        ok = (Xc[..., 2] > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < hgt)
        ok &= rng.random(ok.shape) >= drop
        false = ok & (rng.random(ok.shape) < false_rate)
        uv[false] = rng.uniform([0, 0], [width, hgt], (int(false.sum()), 2))  # false detections anywhere
        name = f"cam{v}"
        for f_idx, p_idx in zip(*np.nonzero(ok), strict=True):
            rows.append((name, int(f_idx), point_names[p_idx], float(uv[f_idx, p_idx, 0]), float(uv[f_idx, p_idx, 1])))
        names.append(name)
        Ks.append(K)
        dists.append(dist)
        Rs.append(R)
        ts.append(t)
        periods.append(period)
        videos.append(
            SubjectVideo(
                name=name,
                width=width,
                height=hgt,
                times=own,
                K=K.copy() if known_K else None,
                dist=(dist.copy() if dist is not None else None) if known_K else None,
            )
        )
    truth = Truth(
        names=names,
        K=Ks,
        dist=dists,
        R=Rs,
        t=ts,
        offsets=[float(offsets[v % len(offsets)]) if v else 0.0 for v in range(n_cameras)],
        periods=periods,
        point_names=point_names,
    )
    return Tracks.from_rows(rows), videos, truth


@dataclass(kw_only=True)
class Handheld:
    """A handheld camera walking an arc around the subject: its tracks and every frame's true pose."""

    name: str
    tracks: Tracks
    times: np.ndarray  # (F,) own seconds
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (F, 3, 3) cam_from_world
    t: np.ndarray  # (F, 3)
    offset: float  # global = own + offset
    width: int = 1920
    height: int = 1080


def handheld(
    *,
    name: str = "phone",
    duration: float = 20.0,
    fps: float = 30.0,
    offset: float = 0.61,
    arc_deg: float = 40.0,
    noise_px: float = 1.0,
    sway_m: float = 0.03,
    seed: int = 1,
) -> Handheld:
    """A phone walked along `arc_deg` of a 4 m circle around `skeleton_motion`'s room, aimed at its middle."""
    rng = np.random.default_rng(seed)
    width, hgt = 1920, 1080
    own = np.arange(0.0, duration - max(offset, 0.0), 1.0 / fps)
    angle = np.radians(20.0 + arc_deg * own / own[-1])
    sway = sway_m * np.sin(2 * np.pi * 0.8 * own)
    centres = np.column_stack([4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.5 + sway])  # (F, 3)
    aim = np.array([0.0, 0.0, 1.0]) + (rng.normal(0, 0.05, (len(own), 3)) if sway_m else 0.0)
    poses = [_look_at(c, a) for c, a in zip(centres, np.broadcast_to(aim, centres.shape), strict=True)]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, hgt / 2], [0, 0, 1.0]])
    X = skeleton_motion(own + offset)  # (F, P, 3)
    Xc = np.einsum("fij,fpj->fpi", R, X) + t[:, None]
    uv = Xc[..., :2] / Xc[..., 2:3] * f + K[:2, 2] + rng.normal(0, noise_px, (*Xc.shape[:2], 2))
    ok = (Xc[..., 2] > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < hgt)
    names = [f"p{i}" for i in range(X.shape[1])]
    rows = [
        (name, int(fi), names[pi], float(uv[fi, pi, 0]), float(uv[fi, pi, 1]))
        for fi, pi in zip(*np.nonzero(ok), strict=True)
    ]
    return Handheld(name=name, tracks=Tracks.from_rows(rows), times=own, K=K, R=R, t=t, offset=offset)


@dataclass(kw_only=True)
class Errors:
    posed: int
    centre_pct: float  # max camera-centre error after a similarity, % of the camera spread
    rotation_deg: float  # max rotation error after the similarity
    offset_frames: float  # max offset error in frames of that video
    focal_pct: float  # max focal error (%)


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: (s, Q, T) with dst ≈ s Q src + T; src, dst: (N, 3)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    Q = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean())
    return s, Q, md - s * Q @ ms


def compare(result: SubjectResult, truth: Truth) -> Errors:
    """Errors of the posed cameras against the truth after the best similarity of the centres."""
    index = [truth.names.index(c.name) for c in result.cameras]
    true_c = truth.centres()[index]
    est_c = np.array([c.centre for c in result.cameras])
    s, Q, T = similarity(est_c, true_c)
    spread = float(np.linalg.norm(true_c - true_c.mean(0), axis=1).max())
    centre = float(np.linalg.norm(s * est_c @ Q.T + T - true_c, axis=1).max() / spread * 100)
    rot, off, foc = 0.0, 0.0, 0.0
    ref = result.cameras[0]
    ref_true = truth.offsets[truth.names.index(ref.name)]
    for cam, i in zip(result.cameras, index, strict=True):
        R_aligned = cam.R @ Q.T  # world_true = Q world_est (up to s, T)
        angle = np.degrees(np.arccos(np.clip((np.trace(R_aligned @ truth.R[i].T) - 1) / 2, -1, 1)))
        rot = max(rot, float(angle))
        # offsets are defined up to a common constant: compare relative to the first posed camera
        err = (cam.offset - ref.offset) - (truth.offsets[i] - ref_true)
        off = max(off, abs(err) / truth.periods[i])
        foc = max(foc, abs(cam.K[0, 0] / truth.K[i][0, 0] - 1) * 100)
    return Errors(posed=len(result.cameras), centre_pct=centre, rotation_deg=rot, offset_frames=off, focal_pct=foc)
