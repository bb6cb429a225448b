"""Which person is which across videos, from the epipolar geometry their keypoints support.

`import-tracks --person all` numbers each video's people on their own (points `person<N>_<keypoint>`): person 1 of
one video may be person 0 of another. For every pair of static videos and every pair of their people, the pair fit
of the subject path (time offset searched, robust epipolar geometry) finds the geometry that pairing's keypoints
support; the same person in two views gives one rigid geometry, two different people do not. Two static cameras
have one geometry and one time offset for all their true pairings, so every pairing is then counted under each
pairing's geometry, and the geometry whose best one-to-one assignment explains the most observations is the
pair's. A pairing is kept when it is the best of its row and column in that table by `MARGIN`; pairings are joined
greedily (most inliers first) into people seen by several videos, never two people of one video in one person.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from dynrecon.beside import map_beside
from sfm.options import MAX_OFFSET_S
from sfm.subject.geometry import sampson
from sfm.subject.model import MIN_INLIERS, NOISE_SCALES_PX, SEED, SubjectVideo
from sfm.subject.observations import VideoObs, build_observations
from sfm.subject.pairs import PairFit, correspondences, fit_pair
from tracking.people import PERSON
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

MARGIN = 1.25  # a pairing's inliers over the best rival pairing of either person in that pair of videos
MIN_SEEN = 0.2  # people seen in fewer of their video's tracked frames are not matched (detector fragments)

Edge = tuple[int, tuple[str, int], tuple[str, int]]  # a kept pairing: its inliers, (video, person) of each side


@dataclass(kw_only=True)
class PeopleAssociation:
    """One number per person across videos (`maps`, for `renumber_people`), and how it was found."""

    groups: list[dict[str, int]]  # per person (its new number): video -> that video's own number
    left_out: dict[str, list[int]]  # per video: its people matched with no other video's
    tables: list[dict[str, Any]] = field(default_factory=list)  # per pair of videos: people and inlier counts
    videos: list[str] = field(default_factory=list)  # the videos whose people were matched (each gets a map)

    @property
    def maps(self) -> dict[str, dict[int, int]]:
        """Per video of a group: its own person numbers -> the numbers across videos (cameras.json `people`)."""
        out: dict[str, dict[int, int]] = {name: {} for name in self.videos}
        for new, group in enumerate(self.groups):
            for video, own in group.items():
                out.setdefault(video, {})[own] = new
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "people": [dict(group) for group in self.groups],
            "left_out": {k: v for k, v in self.left_out.items() if v},
            "pairs": self.tables,
            "margin": MARGIN,
        }


def associate_people(
    tracks: Tracks, videos: list[SubjectVideo], inlier_px: float = NOISE_SCALES_PX[-1], max_offset: float = MAX_OFFSET_S
) -> PeopleAssociation:
    """Number the people of `videos` (static cameras, with their times) consistently across them: each video's map
    from its own person numbers to the numbers across videos (`renumber_people` applies it: people no other video's
    matched left out; other points and videos kept as they are)."""
    # intrinsics are not used: a fundamental matrix per pairing ranks the pairings as well, at a third of the cost
    videos = [replace(v, K=None, dist=None, cam_from_world=None) for v in videos]
    names = [v.name for v in videos]
    person = np.full(len(tracks), -1)
    keypoint = list(tracks.point)
    for i, point in enumerate(tracks.point):
        match = PERSON.match(point)
        if match and tracks.video[i] in names:
            person[i], keypoint[i] = int(match.group(1)), match.group(2)
    video = np.array(tracks.video, dtype=object)
    people = {n: _matched_people(tracks, video == n, person) for n in names}
    pairs = [(a, b) for k, a in enumerate(videos) for b in videos[k + 1 :] if people[a.name] and people[b.name]]

    def one_pair(item: tuple[int, tuple[SubjectVideo, SubjectVideo]]) -> tuple[dict[str, Any], list[Edge]]:
        k, (a, b) = item
        rng = np.random.default_rng([SEED, k])  # per pair of videos: the same draws wherever it runs
        return _match_pair(tracks, video, person, keypoint, a, b, people, rng, max_offset, inlier_px)

    matched_pairs = map_beside(one_pair, list(enumerate(pairs)), "matching people across videos")
    tables = [table for table, _ in matched_pairs]
    edges = [edge for _, pair_edges in matched_pairs for edge in pair_edges]
    groups = _join(edges)
    matched = {(v, own) for group in groups for v, own in group.items()}
    everyone = {n: _all_people(video == n, person) for n in names}
    left_out = {n: [p for p in own if (n, p) not in matched] for n, own in everyone.items()}
    with_people = [n for n, own in everyone.items() if own]
    return PeopleAssociation(groups=groups, left_out=left_out, tables=tables, videos=with_people)


def _match_pair(
    tracks: Tracks,
    video: np.ndarray,
    person: np.ndarray,
    keypoint: list[str],
    a: SubjectVideo,
    b: SubjectVideo,
    people: dict[str, list[int]],
    rng: np.random.Generator,
    max_offset: float,
    inlier_px: float,
) -> tuple[dict[str, Any], list[Edge]]:
    """One pair of videos: its people's inlier table under one geometry (the report's entry) and the pairings it
    keeps (inliers, one video's person, the other's)."""
    shape = (len(people[a.name]), len(people[b.name]))
    obs: dict[tuple[int, int], list[VideoObs]] = {}
    fits: dict[tuple[int, int], PairFit] = {}
    for r, c in np.ndindex(*shape):
        rows = ((video == a.name) & (person == people[a.name][r])) | ((video == b.name) & (person == people[b.name][c]))
        obs[r, c] = _observations(tracks, rows, keypoint, a, b)
        fits[r, c] = fit_pair(obs[r, c][0], obs[r, c][1], 0, 1, max_offset, rng, inlier_px)
    table, source = _shared_geometry(obs, fits, shape, inlier_px)
    log.info("people of %s (rows) and %s (columns), inliers of one geometry:\n%s", a.name, b.name, table)
    edges: list[Edge] = []
    for r, c in zip(*np.nonzero(table >= MIN_INLIERS), strict=True):
        rivals = max(np.delete(table[r], c).max(initial=0), np.delete(table[:, c], r).max(initial=0))
        if table[r, c] >= MARGIN * rivals:
            edges.append((int(table[r, c]), (a.name, people[a.name][r]), (b.name, people[b.name][c])))
    entry = {
        "videos": [a.name, b.name],
        "people": [people[a.name], people[b.name]],
        "inliers": table.tolist(),
        "geometry_of": None if source is None else [people[a.name][source[0]], people[b.name][source[1]]],
    }
    return entry, edges


def _all_people(rows: np.ndarray, person: np.ndarray) -> list[int]:
    return sorted({int(p) for p in person[rows] if p >= 0})


def _matched_people(tracks: Tracks, rows: np.ndarray, person: np.ndarray) -> list[int]:
    """The video's people seen in at least MIN_SEEN of its tracked frames."""
    frames = len(set(tracks.frame[rows].tolist()))
    out = []
    for p in _all_people(rows, person):
        seen = len(set(tracks.frame[rows & (person == p)].tolist()))
        if seen >= MIN_SEEN * frames:
            out.append(p)
    return out


def _observations(
    tracks: Tracks, rows: np.ndarray, keypoint: list[str], a: SubjectVideo, b: SubjectVideo
) -> list[VideoObs]:
    """The two videos' observation arrays of one pairing: its two people's rows, named by keypoint alone."""
    pair = tracks.take(np.flatnonzero(rows))
    pair.point = [keypoint[i] for i in np.flatnonzero(rows)]
    return build_observations(pair, [a, b])[1]


def _shared_geometry(
    obs: dict[tuple[int, int], list[VideoObs]],
    fits: dict[tuple[int, int], PairFit],
    shape: tuple[int, int],
    inlier_px: float,
) -> tuple[np.ndarray, tuple[int, int] | None]:
    """(rows, columns) inlier counts of every pairing under one epipolar geometry and time offset, the one of the
    pairing fits whose best one-to-one assignment explains the most observations (two static cameras have one
    geometry: a wrong pairing can fit a geometry of its own, not the true pairings' one); and the pairing that
    geometry came from (None: no pairing fitted one). A pairing whose own fit is unusable (degenerate: a person
    standing still gives a few distinct positions) counts 0."""
    from scipy.optimize import linear_sum_assignment

    best, best_value, source = np.zeros(shape, dtype=int), -1, None
    for key, fit in fits.items():
        if not fit.usable or fit.E is None:
            continue
        table = np.zeros(shape, dtype=int)
        for r, c in np.ndindex(*shape):
            if fits[r, c].usable:
                table[r, c] = _count(obs[r, c], fit, inlier_px)
        rows, cols = linear_sum_assignment(-table)
        value = int(table[rows, cols].sum())
        if value > best_value:
            best, best_value, source = table, value, key
    return best, source


def _count(obs: list[VideoObs], fit: PairFit, inlier_px: float) -> int:
    """Observations of a pairing within `inlier_px` of `fit`'s epipolar geometry at its time offset."""
    assert fit.E is not None
    xa, xb = correspondences(obs[0], obs[1], fit.shift)
    if not len(xa):
        return 0
    threshold = inlier_px / float(np.sqrt(obs[0].focal * obs[1].focal))
    return int((sampson(fit.E[None], xa, xb)[0] < threshold**2).sum())


def _join(edges: list[Edge]) -> list[dict[str, int]]:
    """Pairings joined into people, most inliers first; a pairing that would put two people of one video in one
    person is skipped. People are numbered by their pairings' inliers (most first)."""
    group_of: dict[tuple[str, int], int] = {}
    groups: list[dict[str, int]] = []
    support: list[int] = []
    for inliers, u, v in sorted(edges, key=lambda e: -e[0]):
        gu, gv = group_of.get(u), group_of.get(v)
        if gu is None and gv is None:
            group_of[u] = group_of[v] = len(groups)
            groups.append({u[0]: u[1], v[0]: v[1]})
            support.append(inliers)
        elif gu is not None and gv is not None:
            if gu == gv or set(groups[gu]) & set(groups[gv]):
                continue
            groups[gu].update(groups[gv])
            support[gu] += support[gv] + inliers
            for member in groups[gv].items():
                group_of[member] = gu
            groups[gv], support[gv] = {}, -1
        else:
            g, w = (gu, v) if gu is not None else (gv, u)
            assert g is not None
            if w[0] in groups[g]:
                continue
            groups[g][w[0]] = w[1]
            group_of[w] = g
            support[g] += inliers
    order = sorted((g for g in range(len(groups)) if groups[g]), key=lambda g: -support[g])
    return [groups[g] for g in order]
