"""Image pairs to match: sequential within each video, and a bounded number of partners across videos.

`match_sequential` orders images by name across folders, so videos would only link near folder boundaries;
these explicit pairs link every video with every other one:
- evenly spaced keyframes of each video, all against all of each other video (a fixed number of pairs);
- optionally, every SfM image with its `partners` most similar images of each other video, by visual words.
So the number of pairs grows linearly with the number of SfM images, not with its square.
"""

from __future__ import annotations

import cv2
import numpy as np

WORDS = 256  # visual words of the retrieval vocabulary
DESCRIPTORS_PER_IMAGE = 500  # SIFT descriptors of each image used for retrieval (a random subset)
VOCABULARY_SAMPLE = 20000  # descriptors the vocabulary is clustered from
SEED = 0


def keyframes(names: list[str], count: int) -> list[str]:
    """`count` evenly spaced names (all when there are fewer)."""
    if len(names) <= count:
        return list(names)
    return [names[i] for i in np.unique(np.round(np.linspace(0, len(names) - 1, count)).astype(int))]


def build_pairs(
    names_of: dict[str, list[str]],
    *,
    overlap: int,
    keyframes: int,
    partners: int = 0,
    words: dict[str, np.ndarray] | None = None,
) -> list[tuple[str, str]]:
    """Unique unordered pairs: (i, i+1..i+overlap) inside each video, keyframes x keyframes across videos, and
    each image with its `partners` most similar images of every other video (`words`: name -> (WORDS,) unit
    vector, from `word_vectors`)."""
    pairs: set[tuple[str, str]] = set()
    for names in names_of.values():
        for i, first in enumerate(names):
            for second in names[i + 1 : i + 1 + overlap]:
                pairs.add(_ordered(first, second))
    keys = {video: _keyframes(names, keyframes) for video, names in names_of.items()}
    videos = list(keys)
    for a, video_a in enumerate(videos):
        for video_b in videos[a + 1 :]:
            pairs.update(_ordered(x, y) for x in keys[video_a] for y in keys[video_b])
    if partners > 0 and words:
        pairs.update(retrieval_pairs(names_of, words, partners))
    return sorted(pairs)


def retrieval_pairs(
    names_of: dict[str, list[str]], words: dict[str, np.ndarray], partners: int
) -> set[tuple[str, str]]:
    """Each image with its `partners` most similar images (cosine of word vectors) of each other video."""
    pairs: set[tuple[str, str]] = set()
    for video_a, names_a in names_of.items():
        query = [n for n in names_a if n in words]
        if not query:
            continue
        vectors_a = np.stack([words[n] for n in query])
        for video_b, names_b in names_of.items():
            found = [n for n in names_b if n in words]
            if video_b == video_a or not found:
                continue
            similarity = vectors_a @ np.stack([words[n] for n in found]).T  # (Qa, Qb)
            best = np.argsort(-similarity, axis=1)[:, :partners]
            pairs.update(_ordered(q, found[j]) for q, row in zip(query, best, strict=True) for j in row)
    return pairs


def word_vectors(descriptors: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """name -> (WORDS,) tf-idf histogram of visual words, unit length, from SIFT descriptors (N, 128) uint8."""
    rng = np.random.default_rng(SEED)
    subsets = {name: _subset(d, rng) for name, d in descriptors.items() if len(d)}
    if not subsets:
        return {}
    everything = np.concatenate(list(subsets.values()))
    count = min(WORDS, len(everything))
    sample = everything[rng.choice(len(everything), min(VOCABULARY_SAMPLE, len(everything)), replace=False)]
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 10, 1.0)
    cv2.setRNGSeed(SEED)
    labels = np.zeros((len(sample), 1), np.int32)
    _, _, found = cv2.kmeans(sample, count, labels, criteria, 1, cv2.KMEANS_PP_CENTERS)
    centres = np.asarray(found, np.float32)
    histograms = {name: _histogram(d, centres) for name, d in subsets.items()}
    present = np.sum([h > 0 for h in histograms.values()], axis=0)
    idf = np.log(len(histograms) / np.maximum(present, 1))
    vectors = {}
    for name, histogram in histograms.items():
        weighted = histogram * idf
        norm = float(np.linalg.norm(weighted))
        vectors[name] = weighted / norm if norm > 0 else weighted
    return vectors


def _subset(descriptors: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(min(N, DESCRIPTORS_PER_IMAGE), 128) float32 rows of one image's descriptors."""
    chosen = descriptors
    if len(descriptors) > DESCRIPTORS_PER_IMAGE:
        chosen = descriptors[rng.choice(len(descriptors), DESCRIPTORS_PER_IMAGE, replace=False)]
    return np.asarray(chosen, np.float32)


def _histogram(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(K,) share of the descriptors (N, 128) nearest each centre (K, 128)."""
    distances = (centres * centres).sum(axis=1)[None, :] - 2.0 * descriptors @ centres.T
    counts = np.bincount(distances.argmin(axis=1), minlength=len(centres)).astype(float)
    return counts / max(len(descriptors), 1)


def _ordered(first: str, second: str) -> tuple[str, str]:
    return (first, second) if first < second else (second, first)


_keyframes = keyframes
