"""Image pairs to match: sequential within each video, and all keyframe pairs across videos.

`match_sequential` orders images by name across folders, so videos would only link near folder boundaries;
these
explicit pairs link every video with every other one through evenly spaced keyframes.
"""

from __future__ import annotations

import numpy as np


def keyframes(names: list[str], count: int) -> list[str]:
    """`count` evenly spaced names (all when there are fewer)."""
    if len(names) <= count:
        return list(names)
    return [names[i] for i in np.unique(np.round(np.linspace(0, len(names) - 1, count)).astype(int))]


def build_pairs(names_of: dict[str, list[str]], *, overlap: int, keyframes: int) -> list[tuple[str, str]]:
    """Unique unordered pairs: (i, i+1..i+overlap) inside each video plus keyframes x keyframes across
    videos."""
    pairs: set[tuple[str, str]] = set()
    for names in names_of.values():
        for i, first in enumerate(names):
            for second in names[i + 1 : i + 1 + overlap]:
                pairs.add((first, second))
    keys = {video: _keyframes(names, keyframes) for video, names in names_of.items()}
    videos = list(keys)
    for a, video_a in enumerate(videos):
        for video_b in videos[a + 1 :]:
            pairs.update((x, y) for x in keys[video_a] for y in keys[video_b])
    return sorted(pairs)


_keyframes = keyframes
