"""Consistent per-video clock offsets from the pairs' measured offsets (weighted, robust least squares)."""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def components(n: int, edges: list[tuple[int, int]]) -> list[set[int]]:
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in edges:
        parent[find(a)] = find(b)
    groups: dict[int, set[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), set()).add(i)
    return list(groups.values())


def solve_offsets(
    n: int, edges: list[tuple[int, int, float, float]], fixed: dict[int, float], tolerance: float
) -> tuple[np.ndarray, list[int]]:
    """edges: (a, b, o_b - o_a, weight). Returns offsets (n,) (NaN where unconnected to `fixed`) and the indices of
    the edges kept; the worst edge is dropped while its residual exceeds `tolerance` and the graph stays connected."""
    kept = list(range(len(edges)))
    while True:
        o = _least_squares(n, [edges[k] for k in kept], fixed)
        if len(kept) == 0:
            return o, kept
        res = np.array([abs(o[edges[k][1]] - o[edges[k][0]] - edges[k][2]) for k in kept])
        res = np.nan_to_num(res)
        worst = int(np.argmax(res))
        if res[worst] <= tolerance:
            return o, kept
        trial = kept[:worst] + kept[worst + 1 :]
        connected = _connected(n, [edges[k] for k in trial], fixed)
        if connected != _connected(n, [edges[k] for k in kept], fixed):
            log.warning("pair offset residual %.3f s kept: dropping it would disconnect a video", res[worst])
            return o, kept
        a, b = edges[kept[worst]][:2]
        log.info("pair %d-%d offset disagrees with the others by %.3f s: dropped", a, b, res[worst])
        kept = trial


def _connected(n: int, edges: list[tuple[int, int, float, float]], fixed: dict[int, float]) -> set[int]:
    out: set[int] = set()
    for group in components(n, [(a, b) for a, b, _, _ in edges]):
        if group & set(fixed):
            out |= group
    return out


def _least_squares(n: int, edges: list[tuple[int, int, float, float]], fixed: dict[int, float]) -> np.ndarray:
    reach = _connected(n, edges, fixed)
    free = [i for i in range(n) if i in reach and i not in fixed]
    o = np.full(n, np.nan)
    for i, v in fixed.items():
        o[i] = v
    if not free:
        return o
    col = {v: j for j, v in enumerate(free)}
    A, y = [], []
    for a, b, d, w in edges:
        if a not in reach or b not in reach:
            continue
        row = np.zeros(len(free))
        rhs = d
        if b in col:
            row[col[b]] += 1
        else:
            rhs -= o[b]
        if a in col:
            row[col[a]] -= 1
        else:
            rhs += o[a]
        sw = np.sqrt(w)
        A.append(row * sw)
        y.append(rhs * sw)
    sol = np.linalg.lstsq(np.array(A), np.array(y), rcond=None)[0]
    o[free] = sol
    return o
