"""Writes `two_cameras.slp` with sleap-io's own `save_slp`, and its truth `two_cameras_truth.csv`.

    pip install sleap-io==0.9.5 && python make_sleap_slp.py

Two videos (`cam1.mp4`, `cam2.mp4`) in one SLEAP project, two tracked mice (mouseA, mouseB), 3 nodes, 6 frames each:
predicted instances with point scores; on cam1 frame 2 mouseA's prediction was corrected by hand (a user instance
from it: the user's points win); on cam2 frame 4 mouseB's tail is not visible. `truth`: every point a reader
should import (video, frame, track, node, x, y, score; score empty for the user's points)."""

import csv

import numpy as np
import sleap_io as sio

skeleton = sio.Skeleton(["head", "thorax", "tail"], edges=[("head", "thorax"), ("thorax", "tail")])
videos = [sio.Video(filename=f"cam{k}.mp4", open_backend=False) for k in (1, 2)]
tracks = [sio.Track("mouseA"), sio.Track("mouseB")]
rng = np.random.default_rng(5)
frames, rows = [], []
for video in videos:
    name = video.filename.removesuffix(".mp4")
    for f in range(6):
        instances = []
        for track in tracks:
            xy = rng.uniform(20, 600, (3, 2)).round(2)
            scores = rng.uniform(0.3, 1.0, 3).round(3)
            if name == "cam2" and f == 4 and track.name == "mouseB":
                xy[2] = np.nan  # not visible
            predicted = sio.PredictedInstance.from_numpy(
                xy, skeleton=skeleton, point_scores=scores, score=0.9, track=track, tracking_score=0.8
            )
            instances.append(predicted)
            if name == "cam1" and f == 2 and track.name == "mouseA":
                fixed = (xy + 3.0).round(2)
                instances.append(sio.Instance.from_numpy(fixed, skeleton=skeleton, track=track))
                instances[-1].from_predicted = predicted
                xy, scores = fixed, [None] * 3
            for n, node in enumerate(skeleton.node_names):
                if np.isfinite(xy[n]).all():
                    rows.append([name, f, track.name, node, xy[n, 0], xy[n, 1], "" if scores[n] is None else scores[n]])
        frames.append(sio.LabeledFrame(video=video, frame_idx=f, instances=instances))
labels = sio.Labels(labeled_frames=frames, videos=videos, skeletons=[skeleton], tracks=tracks)
sio.save_slp(labels, "two_cameras.slp")
with open("two_cameras_truth.csv", "w", newline="") as handle:
    writer = csv.writer(handle)
    writer.writerow(["video", "frame", "track", "node", "x", "y", "score"])
    writer.writerows(rows)
