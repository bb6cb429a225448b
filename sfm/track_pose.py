"""In-between frames posed by tracking instead of SIFT per frame.

The registered keyframes on both sides of a frame lend their background features (keypoints with a 3D point in
the model, started at the 3D point's projection). Pyramidal LK with a forward-backward check carries them frame to
frame at a working resolution (long side `WORK_LONG_SIDE`), the moving subject masked, one chain from each keyframe.
PnP (LO-RANSAC + refinement, the video's camera fixed) against their 3D points poses each wanted frame from both
chains' features, or from one chain where the other lost them. Frames that no chain poses come back with a reason,
for the SIFT path (`sfm.localize`). No pose is ever interpolated.

Where the camera walks away from its keyframe, a chain's features leave the view. When fewer than `FRESH_SURVIVAL`
of them survive, the chain poses that frame by itself and starts carrying fresh corners from it (2D only); when
fewer than `PROMOTE_SURVIVAL` survive and the frame is posed by PnP with many inliers, that frame is promoted to a
new keyframe of the tracking: the fresh corners are triangulated between the two posed frames (reprojection and
angle checks, `sfm.triangulate`), and the chain goes on from it with the surviving model points plus the new ones.
The SfM model itself is not changed."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from sfm.frames import Resize
from sfm.localize import Localized, absolute_pose
from sfm.triangulate import triangulate
from sfm.video import read_frames

log = logging.getLogger(__name__)

WORK_LONG_SIDE = 960  # tracking resolution (pixels of the long side); poses stay in full-resolution pixels
MAX_POINTS = 300  # features carried per keyframe, spread over the image: LK's cost grows with their number
GRID = (16, 9)  # cells (x, y) over which the carried features are spread, for a well-conditioned PnP
LK_WINDOW = 15
LK_LEVELS = 3
LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
MAX_FB_ERROR = 0.7  # working pixels between a point and its forward-backward round trip
MIN_INLIER_RATIO = 0.5  # PnP inliers / tracked points below this: the tracks are not trusted
MAX_ERROR = 4.0  # RANSAC threshold, SfM pixels (as the SIFT path)
FRESH_SURVIVAL = 0.8  # share of a chain's features still tracked under which it starts carrying fresh corners
PROMOTE_SURVIVAL = 0.5  # ... under which a well-posed frame becomes a new keyframe of the chain
PROMOTE_INLIER_RATIO = 0.8  # a frame is promoted only when this share of its tracked features are PnP inliers
PROMOTE_MIN_INLIERS = 2  # ... and at least this many times --min-inliers of them
MIN_TRIANGULATION_ANGLE = 2.0  # degrees between the two rays of a new point (COLMAP's mapper uses 1.5)
MAX_TRIANGULATION_ERROR = 2.0  # SfM pixels, in both views, for a new point

Masks = Callable[[int], np.ndarray | None]  # frame -> (H, W) uint8 mask in SfM pixels (0 = subject), or None


@dataclass(kw_only=True)
class Seed:
    """A registered keyframe's background features. uv: (N, 2) original OpenCV pixels; xyz: (N, 3) world;
    weight: (N,) how much to prefer each (its 3D point's track length)."""

    frame: int
    uv: np.ndarray
    xyz: np.ndarray
    weight: np.ndarray


@dataclass(kw_only=True)
class TrackedPose:
    """A frame posed from tracked features: the PnP result (pose, inliers, mean error in SfM pixels)."""

    frame: int
    located: Localized
    tracked: int  # features that reached this frame


@dataclass(kw_only=True)
class VideoTracking:
    """What tracking gave one video: posed frames, the frames left for SIFT with the reason, and the frames
    promoted to keyframes of the tracking (frame -> new 3D points triangulated for it)."""

    posed: dict[int, TrackedPose] = field(default_factory=dict)
    failed: dict[int, str] = field(default_factory=dict)
    added: dict[int, int] = field(default_factory=dict)


def seed_from_image(rec: pycolmap.Reconstruction, image: pycolmap.Image, sfm_resize: Resize) -> Seed:
    """The 3D points a registered image observes, at their projections in it (original OpenCV pixels): LK starts
    at the model's projection, not at the detection, the 3D point being the better estimate."""
    observed = [p.point3D_id for p in image.points2D if p.has_point3D()]
    if not observed:
        return Seed(frame=int(Path(image.name).stem), uv=np.zeros((0, 2)), xyz=np.zeros((0, 3)), weight=np.zeros(0))
    xyz = np.array([rec.points3D[o].xyz for o in observed], dtype=float).reshape(-1, 3)
    pose = image.cam_from_world()
    in_cam = xyz @ pose.rotation.matrix().T + pose.translation
    xy = np.asarray(rec.cameras[image.camera_id].img_from_cam(in_cam), dtype=float).reshape(-1, 2)
    weight = np.array([rec.points3D[o].track.length() for o in observed], dtype=float)
    frame = int(Path(image.name).stem)
    return Seed(frame=frame, uv=colmap_to_original(xy, sfm_resize), xyz=xyz, weight=weight)


def colmap_to_original(xy: np.ndarray, sfm_resize: Resize) -> np.ndarray:
    """(N, 2) COLMAP pixels of the SfM frames (pixel centre at 0.5) -> original OpenCV pixels (centre at 0)."""
    return np.asarray(xy, dtype=float) / sfm_resize.scale - 0.5


def original_to_colmap(uv: np.ndarray, sfm_resize: Resize) -> np.ndarray:
    """(N, 2) original OpenCV pixels -> COLMAP pixels of the SfM frames, where the model's camera lives."""
    return (np.asarray(uv, dtype=float) + 0.5) * sfm_resize.scale


def spread(uv: np.ndarray, weight: np.ndarray, width: float, height: float, count: int = MAX_POINTS) -> np.ndarray:
    """Indices of at most `count` of the points uv (N, 2), taken round-robin over a grid of cells, the heaviest
    first in each cell: a few textured corners must not take every slot."""
    if len(uv) <= count:
        return np.arange(len(uv))
    cx = np.clip((uv[:, 0] / width * GRID[0]).astype(int), 0, GRID[0] - 1)
    cy = np.clip((uv[:, 1] / height * GRID[1]).astype(int), 0, GRID[1] - 1)
    cell = cy * GRID[0] + cx
    order = np.lexsort((-weight, cell))  # by cell, heaviest first within a cell
    sorted_cells = cell[order]
    starts = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.arange(len(order)) - starts  # position within its cell
    chosen = order[np.lexsort((-weight[order], rank))][:count]
    return np.sort(chosen)


def work_image(image: np.ndarray, work: Resize) -> np.ndarray:
    """(H, W) uint8 grey image at the working resolution of a BGR frame."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    if work.scale != 1.0:
        grey = cv2.resize(grey, (work.width, work.height), interpolation=cv2.INTER_AREA)
    return grey


def lk_step(previous: np.ndarray, current: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) of `previous` found in `current` (working pixels): (new points (N, 2), kept (N,) bool) after
    the forward-backward check."""
    if len(points) == 0:
        return points, np.zeros(0, bool)
    window = (LK_WINDOW, LK_WINDOW)
    p0 = points.astype(np.float32).reshape(-1, 1, 2)
    p1, status, _ = (
        np.asarray(a)
        for a in cv2.calcOpticalFlowPyrLK(
            previous, current, p0, p0.copy(), winSize=window, maxLevel=LK_LEVELS, criteria=LK_CRITERIA
        )
    )
    back, status_back, _ = (
        np.asarray(a)
        for a in cv2.calcOpticalFlowPyrLK(
            current, previous, p1, p0.copy(), winSize=window, maxLevel=LK_LEVELS, criteria=LK_CRITERIA
        )
    )
    round_trip = np.linalg.norm(back - p0, axis=2).ravel()
    new = p1.reshape(-1, 2).astype(float)
    inside = (new[:, 0] >= 0) & (new[:, 1] >= 0) & (new[:, 0] <= current.shape[1] - 1)
    inside &= new[:, 1] <= current.shape[0] - 1
    kept = (status.ravel() == 1) & (status_back.ravel() == 1) & (round_trip < MAX_FB_ERROR) & inside
    return new, kept


def outside_mask(uv: np.ndarray, mask: np.ndarray | None, sfm_resize: Resize) -> np.ndarray:
    """(N,) bool: the points uv (N, 2) (original pixels) that the mask (SfM pixels, 0 = subject) does not cover."""
    if mask is None or len(uv) == 0:
        return np.ones(len(uv), bool)
    small = np.round(sfm_resize.to_small(uv)).astype(int)
    x = np.clip(small[:, 0], 0, mask.shape[1] - 1)
    y = np.clip(small[:, 1], 0, mask.shape[0] - 1)
    return np.asarray(mask[y, x] > 0)


@dataclass(kw_only=True)
class _Fresh:
    """Corners carried from a posed frame of a chain, without 3D points yet. start: (N, 2) original pixels at
    `frame`; now: (N, 2) working pixels where they are in the current frame."""

    frame: int
    pose: pycolmap.Rigid3d  # cam_from_world of `frame`
    start: np.ndarray
    now: np.ndarray


@dataclass(kw_only=True)
class _Chain:
    """Features of one keyframe being carried through a segment, frame by frame (lazily, so that a chain costs
    only the frames it is asked for)."""

    seed: Seed
    frames: list[int]  # in tracking order, each next to the previous; the seed's frame is not in it
    images: dict[int, np.ndarray]  # frame -> working grey image (seed frame included)
    work: Resize
    sfm_resize: Resize
    masks: Masks
    min_points: int
    camera: pycolmap.Camera
    steps: Iterator[tuple[int, np.ndarray, np.ndarray]] | None = None
    done: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # frame -> (uv, xyz)
    lost_at: int | None = None
    added: dict[int, int] = field(default_factory=dict)  # frames promoted to keyframes -> new 3D points

    def reach(self, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(uv (M, 2) original pixels, xyz (M, 3)) of the features that reached `frame`, or None when the chain
        lost them before."""
        if self.steps is None:
            self.steps = self._carry()
        while frame not in self.done and self.lost_at is None:
            try:
                next(self.steps)
            except StopIteration:
                break
        return self.done.get(frame)

    def _to_original(self, points: np.ndarray) -> np.ndarray:
        return (points + 0.5) / self.work.scale - 0.5

    def _carry(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        size = (self.work.width / self.work.scale, self.work.height / self.work.scale)
        chosen = spread(self.seed.uv, self.seed.weight, *size, count=MAX_POINTS)
        points = self.work.to_small(self.seed.uv[chosen])
        xyz = self.seed.xyz[chosen]
        started = len(points)
        fresh: _Fresh | None = None
        previous = self.images[self.seed.frame]
        for frame in self.frames:
            current = self.images[frame]
            carried = len(points)
            both = points if fresh is None else np.concatenate([points, fresh.now])
            moved, kept = lk_step(previous, current, both)
            kept &= outside_mask(self._to_original(moved), self.masks(frame), self.sfm_resize)
            points, xyz = moved[:carried][kept[:carried]], xyz[kept[:carried]]
            if fresh is not None:
                fresh.start, fresh.now = fresh.start[kept[carried:]], moved[carried:][kept[carried:]]
            uv = self._to_original(points)
            survival = len(points) / max(started, 1)
            if fresh is None and survival < FRESH_SURVIVAL and len(points) >= self.min_points:
                fresh = self._fresh(frame, current, uv, xyz)
            elif fresh is not None and survival < PROMOTE_SURVIVAL:
                promoted = self._promote(frame, fresh, uv, xyz)
                if promoted is not None:
                    points, xyz = promoted
                    uv, started, fresh = self._to_original(points), len(points), None
            if len(points) < self.min_points:
                self.lost_at = frame
                return
            self.done[frame] = (uv, xyz)
            yield frame, uv, xyz
            previous = current

    def _own_pose(self, uv: np.ndarray, xyz: np.ndarray, min_inliers: int) -> Localized:
        """PnP of the current frame from this chain's features alone (uv (M, 2) original pixels, xyz (M, 3))."""
        return absolute_pose(
            original_to_colmap(uv, self.sfm_resize), xyz, self.camera, min_inliers=min_inliers, max_error=MAX_ERROR
        )

    def _fresh(self, frame: int, image: np.ndarray, uv: np.ndarray, xyz: np.ndarray) -> _Fresh | None:
        """Corners of `frame` (off the subject) to carry from here, when the chain poses `frame` by itself."""
        located = self._own_pose(uv, xyz, self.min_points)
        if located.cam_from_world is None or located.inliers < PROMOTE_INLIER_RATIO * len(uv):
            return None
        corners = cv2.goodFeaturesToTrack(
            image, maxCorners=MAX_POINTS, qualityLevel=0.01, minDistance=max(image.shape) / 60
        )
        if corners is None:
            return None
        now = np.asarray(corners, float).reshape(-1, 2)
        start = self._to_original(now)
        keep = outside_mask(start, self.masks(frame), self.sfm_resize)
        return _Fresh(frame=frame, pose=located.cam_from_world, start=start[keep], now=now[keep])

    def _promote(
        self, frame: int, fresh: _Fresh, uv: np.ndarray, xyz: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """`frame` as a new keyframe of the chain: (points (M, 2) working pixels, xyz (M, 3)), its surviving
        model points (PnP inliers) and the fresh corners triangulated against `fresh.frame`; None when the frame
        is not posed well enough or too few new points pass the checks."""
        located = self._own_pose(uv, xyz, PROMOTE_MIN_INLIERS * self.min_points)
        if located.cam_from_world is None or located.inlier_mask is None:
            return None
        if located.inliers < PROMOTE_INLIER_RATIO * len(uv):
            return None
        new_xyz, ok = triangulate(
            self.camera,
            fresh.pose,
            located.cam_from_world,
            original_to_colmap(fresh.start, self.sfm_resize),
            original_to_colmap(self._to_original(fresh.now), self.sfm_resize),
            max_error=MAX_TRIANGULATION_ERROR,
            min_angle_deg=MIN_TRIANGULATION_ANGLE,
        )
        if ok.sum() < self.min_points:
            return None
        kept = located.inlier_mask
        points = np.concatenate([self.work.to_small(uv[kept]), fresh.now[ok]])
        world = np.concatenate([xyz[kept], new_xyz[ok]])
        # The model's points first in each cell: the new ones carry the two poses' errors.
        weight = np.concatenate([np.full(int(kept.sum()), 2.0), np.ones(int(ok.sum()))])
        chosen = spread(points, weight, float(self.work.width), float(self.work.height), count=MAX_POINTS)
        self.added[frame] = int(ok.sum())
        log.debug(
            "frame %d promoted to a keyframe of the chain from %d: %d new points", frame, self.seed.frame, ok.sum()
        )
        return points[chosen], world[chosen]


def _pose(
    frame: int, chains: list[_Chain], camera: pycolmap.Camera, min_inliers: int
) -> tuple[TrackedPose | None, str]:
    """PnP of one frame from the features that `chains` carried to it; (None, why) when they lost them or PnP
    refused."""
    reached = [r for r in (c.reach(frame) for c in chains) if r is not None]
    source = " and ".join(str(c.seed.frame) for c in chains)
    if not reached:
        return None, f"tracking from frame {source} lost the features at frame {chains[0].lost_at}"
    uv = np.concatenate([r[0] for r in reached])
    xyz = np.concatenate([r[1] for r in reached])
    located = absolute_pose(
        original_to_colmap(uv, chains[0].sfm_resize), xyz, camera, min_inliers=min_inliers, max_error=MAX_ERROR
    )
    if located.cam_from_world is None:
        return None, f"tracked from frame {source}: {located.reason}"
    if located.inliers < MIN_INLIER_RATIO * len(uv):
        return None, f"tracked from frame {source}: only {located.inliers} PnP inliers of {len(uv)} tracks"
    return TrackedPose(frame=frame, located=located, tracked=len(uv)), ""


@dataclass(kw_only=True)
class _Segment:
    """Frames strictly between two keyframes (or before the first / after the last: one side is None)."""

    before: int | None
    after: int | None
    inner: list[int]  # every frame between them, ascending
    needed: list[int]  # the inner frames that want a pose

    @property
    def last(self) -> int:
        return self.after if self.after is not None else self.inner[-1]


def segments(keyframes: list[int], needed: list[int]) -> list[_Segment]:
    """The stretches between consecutive keyframes that hold needed frames (keyframes and needed ascending)."""
    out = []
    bounds: list[int | None] = [None, *keyframes, None]
    for before, after in pairwise(bounds):
        low = -1 if before is None else before
        high = np.inf if after is None else after
        inside = [f for f in needed if low < f < high]
        if not inside:
            continue
        start = inside[0] if before is None else before + 1
        end = inside[-1] if after is None else after - 1
        out.append(_Segment(before=before, after=after, inner=list(range(start, end + 1)), needed=inside))
    return out


def _solve_segment(
    segment: _Segment,
    seeds: dict[int, Seed],
    images: dict[int, np.ndarray],
    make_chain: Callable[[Seed, list[int]], _Chain],
    camera: pycolmap.Camera,
    min_inliers: int,
) -> VideoTracking:
    """Each needed frame from both keyframes' chains, or from one where the other fails."""
    chains = []
    if segment.before is not None:
        chains.append(make_chain(seeds[segment.before], segment.inner))
    if segment.after is not None:
        chains.append(make_chain(seeds[segment.after], segment.inner[::-1]))
    result = VideoTracking()
    for frame in segment.needed:
        order = sorted(chains, key=lambda c: abs(c.seed.frame - frame))
        # Both keyframes' features together first (twice the points, two keyframes' errors averaged); then
        # each side alone, nearer first, where the other lost its features or misled PnP.
        tries = [order, *([c] for c in order)] if len(order) > 1 else [order]
        reasons = []
        for chain in tries:
            posed, why = _pose(frame, chain, camera, min_inliers)
            if posed is not None:
                result.posed[frame] = posed
                break
            reasons.append(why)
        else:
            result.failed[frame] = "; ".join(reasons)
    for side in chains:
        result.added.update(side.added)
    return result


def track_video(
    path: Path,
    seeds: dict[int, Seed],
    needed: list[int],
    camera: pycolmap.Camera,
    sfm_resize: Resize,
    masks: Masks,
    *,
    min_inliers: int,
    desc: str = "tracking",
) -> VideoTracking:
    """Poses of the `needed` frames of one video from its keyframes' `seeds` (frame -> Seed), decoding the video
    once in order; frames it cannot pose come back in `failed` with the reason."""
    work = Resize.for_video_size(
        round(sfm_resize.width / sfm_resize.scale), round(sfm_resize.height / sfm_resize.scale), WORK_LONG_SIDE
    )
    result = VideoTracking()
    if not seeds:
        result.failed = {f: "no registered keyframe in this video" for f in needed}
        return result
    parts = segments(sorted(seeds), sorted(needed))
    to_decode = sorted(
        {f for s in parts for f in s.inner} | {k for s in parts for k in (s.before, s.after) if k is not None}
    )
    ends = {s.last: s for s in parts}
    images: dict[int, np.ndarray] = {}
    mask_cache: dict[int, np.ndarray | None] = {}

    def cached_mask(frame: int) -> np.ndarray | None:
        if frame not in mask_cache:  # both chains of a segment pass every frame: read its mask once
            mask_cache[frame] = masks(frame)
        return mask_cache[frame]

    def make_chain(seed: Seed, frames: list[int]) -> _Chain:
        return _Chain(
            seed=seed,
            frames=frames,
            images=images,
            work=work,
            sfm_resize=sfm_resize,
            masks=cached_mask,
            min_points=min_inliers,
            camera=camera,
        )

    progress = tqdm(total=len(needed), desc=desc, unit="frame", leave=False)
    for frame, image in read_frames(path, np.asarray(to_decode, dtype=np.int64)):
        images[frame] = work_image(image, work)
        segment = ends.get(frame)
        if segment is None:
            continue
        solved = _solve_segment(segment, seeds, images, make_chain, camera, min_inliers)
        result.posed.update(solved.posed)
        result.failed.update(solved.failed)
        result.added.update(solved.added)
        progress.update(len(segment.needed))
        for old in [f for f in images if f < frame]:
            del images[old]  # a segment's frames are not needed after it: memory stays one segment
        mask_cache.clear()
    progress.close()
    return result
