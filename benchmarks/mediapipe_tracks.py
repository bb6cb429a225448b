"""MediaPipe Pose keypoints of videos as a tracks.csv: a second real detector for the subject path's benchmarks.

    pip install mediapipe==0.10.21   # in a separate venv: its legacy Pose solution ships its models in the wheel
    python benchmarks/mediapipe_tracks.py OUT.csv VIDEO...

Per frame the one person MediaPipe Pose finds (`model_complexity=1`, video mode), its 33 landmarks in pixels of the
decoded frame (OpenCV's convention: pixel centres at integers), those with visibility >= MIN_VISIBILITY and within
5 % of the image, `source=mediapipe`, `score` = visibility. Point names are MediaPipe's, lower case (`left_wrist`).
Made the committed tests/data/pose2sim/mediapipe_tracks.csv and tests/data/caliscope/mediapipe_tracks.csv.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import cv2

MIN_VISIBILITY = 0.5


def main(argv: list[str]) -> int:
    import mediapipe as mp  # not a dependency of dynrecon

    if len(argv) < 2:
        print(__doc__)
        return 2
    names = [landmark.name.lower() for landmark in mp.solutions.pose.PoseLandmark]
    out, videos = Path(argv[0]), [Path(p) for p in argv[1:]]
    with out.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["video", "frame", "point", "x", "y", "source", "score"])
        for video in videos:
            capture = cv2.VideoCapture(str(video))
            frame = 0
            with mp.solutions.pose.Pose(static_image_mode=False, model_complexity=1) as pose:
                while True:
                    ok, image = capture.read()
                    if not ok:
                        break
                    height, width = image.shape[:2]
                    found = pose.process(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
                    landmarks = found.pose_landmarks.landmark if found.pose_landmarks else []
                    for name, lm in zip(names[: len(landmarks)], landmarks, strict=True):
                        x, y = lm.x * width - 0.5, lm.y * height - 0.5  # normalized image -> pixel centres
                        inside = -0.05 * width < x < 1.05 * width and -0.05 * height < y < 1.05 * height
                        if lm.visibility >= MIN_VISIBILITY and inside:
                            writer.writerow(
                                [video.stem, frame, name, f"{x:.1f}", f"{y:.1f}", "mediapipe", f"{lm.visibility:.3f}"]
                            )
                    frame += 1
            print(f"{video}: {frame} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
