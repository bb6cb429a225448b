"""The skeleton file: named points and the connections drawn between them (see docs/formats.md).

    {"points": ["head", "hip"], "connections": [["head", "hip"]]}

The labeling page's file (`--skeleton`, and the same keys in `WS/labeling.json`); the solver's recording and the
pipeline read it too, which is why it is a module of its own that imports only the ground.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from dynrecon.errors import InputError
from dynrecon.readers import read_json, shown


@dataclass(kw_only=True)
class Skeleton:
    """Named points in display order and the pairs drawn as lines between them."""

    points: list[str] = field(default_factory=list)
    connections: list[tuple[str, str]] = field(default_factory=list)

    def add_point(self, name: str) -> None:
        if name not in self.points:
            self.points.append(name)

    def merge(self, other: Skeleton) -> None:
        for name in other.points:
            self.add_point(name)
        for pair in other.connections:
            if pair not in self.connections and pair[::-1] not in self.connections:
                self.connections.append(pair)

    def rename(self, old: str, new: str) -> None:
        self.points = [new if p == old else p for p in self.points]
        self.connections = [(new if a == old else a, new if b == old else b) for a, b in self.connections]


def valid_point_name(name: str) -> bool:
    """Names go into CSV cells and the page; keep them printable, short and free of separators."""
    return (
        bool(name)
        and len(name) <= 64
        and name == name.strip()
        and name.isprintable()
        and not any(c in name for c in ",\"'\\/<>")
    )


def parse_points(text: str) -> Skeleton:
    """`--points a,b,c`."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if not valid_point_name(n)]
    if bad:
        raise InputError(
            None,
            f"--points: invalid point name {bad[0]!r}",
            fix="names are up to 64 printable characters without , \" ' \\ / < >",
        )
    return Skeleton(points=list(dict.fromkeys(names)))


def read_skeleton(path: Path) -> Skeleton:
    """Skeleton JSON `{"points": [...], "connections": [["a", "b"], ...]}`; connections may add points."""
    data = read_json(path, missing_fix="give the path of a skeleton JSON file")
    skeleton = skeleton_from_json(path, data)
    if not skeleton.points:  # a file of other keys would draw nothing, silently
        raise InputError(
            path, "no 'points' or 'connections'", fix='expected {"points": ["a", "b"], "connections": [["a", "b"]]}'
        )
    return skeleton


def skeleton_from_json(path: Path, data: object) -> Skeleton:
    """The skeleton of a parsed JSON document (a skeleton file, or labeling.json's points and connections)."""
    fix = 'expected {"points": ["a", "b"], "connections": [["a", "b"]]}'
    if not isinstance(data, dict):
        raise InputError(path, "top level is not an object", fix=fix)
    points = data.get("points", [])
    connections = data.get("connections", [])
    if not isinstance(points, list) or not all(isinstance(p, str) and valid_point_name(p) for p in points):
        raise InputError(path, "'points' must be a list of point names", fix=fix)
    skeleton = Skeleton(points=list(dict.fromkeys(points)))
    if not isinstance(connections, list):
        raise InputError(path, "'connections' must be a list of pairs", fix=fix)
    for i, pair in enumerate(connections):
        if (
            not (
                isinstance(pair, list | tuple)
                and len(pair) == 2
                and all(isinstance(p, str) and valid_point_name(p) for p in pair)
            )
            or pair[0] == pair[1]
        ):
            raise InputError(
                path, f"connection {i} ({shown(pair)}) is not a pair of two different point names", fix=fix
            )
        skeleton.add_point(pair[0])
        skeleton.add_point(pair[1])
        skeleton.connections.append((pair[0], pair[1]))
    return skeleton
