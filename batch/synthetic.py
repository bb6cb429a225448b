"""Small simulated capture folders for the batch's tests and benchmark: static phones with a calibration file,
short videos of white dots on a dark background, and ready tracks or sparse labels.

The layout is the one `dynrecon batch` reads (docs/formats.md, "Capture folder"). Cheap by design: a few hundred
small frames per capture, so that a batch of several captures runs in seconds.
"""

from __future__ import annotations

import csv
import enum
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from reconstruct.outputs.mocap import Mocap
from sfm.calibration import StaticCamera, write_toml
from simulation.phones import PhoneCaptureOptions, simulate_phones
from tracking.tracks import Tracks, write_tracks

MM_PER_M = 1000.0  # the simulation is in mm, calibration TOML files in metres


class Inputs(enum.Enum):
    """What a simulated capture gives besides its videos and calibration."""

    TRACKS = "tracks"  # tracks.csv: no tracking
    LABELS = "labels"  # labels.csv on every `label_step`-th frame: the batch tracks each video


@dataclass(kw_only=True)
class SimulatedCaptureOptions:
    seed: int = 0
    inputs: Inputs = Inputs.TRACKS
    seconds: float = 1.5  # length of the motion
    points: int = 6
    fps: tuple[float, ...] = (30.0, 25.0, 20.0)  # one static phone per rate
    image_size: int = 320  # pixels (width = height)
    label_step: int = 4  # labels on every Nth frame of each video (Inputs.LABELS)
    dot_radius: int = 3  # pixels


def smooth_mocap(seconds: float, points: int, seed: int, rate: float = 120.0) -> Mocap:
    """`points` markers on smooth random paths (sums of slow sines) around the origin, mm."""
    rng = np.random.default_rng(seed)
    times = np.arange(round(seconds * rate)) / rate
    base = rng.normal(0.0, 300.0, (points, 3))
    amplitude = rng.uniform(50.0, 250.0, (3, points, 3))
    frequency = rng.uniform(0.2, 1.2, (3, points, 3))
    phase = rng.uniform(0.0, 2 * np.pi, (3, points, 3))
    waves = amplitude[None] * np.sin(2 * np.pi * frequency[None] * times[:, None, None, None] + phase[None])
    xyz = base[None] + waves.sum(axis=1)
    return Mocap(xyz=xyz, rate=rate, marker_names=[f"p{i}" for i in range(points)], times=times)


def simulated_capture(out: str | Path, options: SimulatedCaptureOptions | None = None) -> Path:
    """Write a capture folder into `out`: cam*.avi, calibration.toml, and tracks.csv or labels.csv; returns `out`."""
    options = options or SimulatedCaptureOptions()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mocap = smooth_mocap(options.seconds, options.points, options.seed)
    capture, _ = simulate_phones(
        mocap,
        PhoneCaptureOptions(
            cameras=len(options.fps),
            fps=options.fps,
            offset_s=(0.0, 0.3),
            image_size=options.image_size,
            focal_px=float(options.image_size),
            seed=options.seed,
        ),
    )
    tracks = capture.tracks
    cameras = []
    for video in capture.cameras.videos:
        first = video.frames[0]
        frames = 1 + max(f.frame for f in video.frames)
        _write_video(out / f"{video.name}.avi", tracks, video.name, frames, video.fps or 30.0, options)
        cameras.append(
            StaticCamera(
                name=video.name,
                width=video.width,
                height=video.height,
                K=first.K,
                dist=np.zeros(4),
                R=first.R,
                t=first.t / MM_PER_M,
            )
        )
    write_toml(out / "calibration.toml", cameras)
    if options.inputs is Inputs.TRACKS:
        write_tracks(out / "tracks.csv", tracks)
    else:
        _write_labels(out / "labels.csv", tracks, options.label_step)
    return out


def _write_video(
    path: Path, tracks: Tracks, name: str, frames: int, fps: float, options: SimulatedCaptureOptions
) -> None:
    """White dots where the points project, on a dark background (MJPG: small files, fast to decode)."""
    size = options.image_size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (size, size))
    try:
        rows = [i for i in range(len(tracks)) if tracks.video[i] == name]
        by_frame: dict[int, list[np.ndarray]] = {}
        for i in rows:
            by_frame.setdefault(int(tracks.frame[i]), []).append(tracks.xy[i])
        for frame in range(frames):
            image = np.full((size, size, 3), 30, np.uint8)
            for x, y in by_frame.get(frame, []):
                cv2.circle(image, (round(x), round(y)), options.dot_radius, (255, 255, 255), -1, cv2.LINE_AA)
            writer.write(image)
    finally:
        writer.release()


def _write_labels(path: Path, tracks: Tracks, step: int) -> None:
    """The tracks' positions on every `step`-th frame as clicks (labels.csv)."""
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(["video", "frame", "point", "x", "y", "source"])
        for i in range(len(tracks)):
            if int(tracks.frame[i]) % step == 0:
                x, y = tracks.xy[i]
                writer.writerow(
                    [tracks.video[i], int(tracks.frame[i]), tracks.point[i], f"{x:.3f}", f"{y:.3f}", "label"]
                )
