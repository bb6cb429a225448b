"""Writes this folder's SLEAP analysis HDF5 files with sleap-io's own writer, and their truth.

    pip install sleap-io==0.9.5 && python make_sleap_files.py

Two mice (tracks mouseA, mouseB) with 3 nodes over 12 frames of video `cam1`: mouseB is missing on frames 3-5 and
mouseA's thorax on frame 7. `cam1.analysis.h5`: SLEAP's layout (sleap-io's default `matlab` preset);
`cam1.standard.analysis.h5`: the `standard` preset (frame-first, its `dims` attribute says so). `truth.csv`: every
point written (frame, track, node, x, y, score)."""

import csv

import numpy as np
import sleap_io as sio

skeleton = sio.Skeleton(["head", "thorax", "tail"], edges=[("head", "thorax"), ("thorax", "tail")])
video = sio.Video(filename="cam1.mp4", open_backend=False)
tracks = [sio.Track("mouseA"), sio.Track("mouseB")]
rng = np.random.default_rng(0)
frames, rows = [], []
for f in range(12):
    instances = []
    for track in tracks:
        if track.name == "mouseB" and 3 <= f <= 5:
            continue
        xy = rng.uniform(20, 600, (3, 2)).round(2)
        scores = rng.uniform(0.3, 1.0, 3).round(3)
        if track.name == "mouseA" and f == 7:
            xy[1] = np.nan
        instances.append(
            sio.PredictedInstance.from_numpy(
                xy, skeleton=skeleton, point_scores=scores, score=0.9, track=track, tracking_score=0.8
            )
        )
        for n, node in enumerate(skeleton.node_names):
            if np.isfinite(xy[n]).all():
                rows.append([f, track.name, node, xy[n, 0], xy[n, 1], scores[n]])
    frames.append(sio.LabeledFrame(video=video, frame_idx=f, instances=instances))
labels = sio.Labels(labeled_frames=frames, videos=[video], skeletons=[skeleton], tracks=tracks)
sio.save_analysis_h5(labels, "cam1.analysis.h5")
sio.save_analysis_h5(labels, "cam1.standard.analysis.h5", preset="standard")
with open("truth.csv", "w", newline="") as handle:
    writer = csv.writer(handle)
    writer.writerow(["frame", "track", "node", "x", "y", "score"])
    writer.writerows(rows)
