"""points3d.csv and sequencing.json are built from text pieces: the same bytes as csv.writer and json.dumps."""

import csv
import io
import json
import math

import numpy as np

from reconstruct.outputs.points import COUNT_COLUMNS, FramePoints, Sequencing, write_points, write_sequencing

AWKWARD = [0.0, -0.0, 1e16, 1e-5, 1e-4, 123456789012345678.0, 5e-324, -1.5, math.nan, math.inf, -math.inf, 0.1]


def _csv_reference(points: FramePoints) -> str:
    """points3d.csv as csv.writer writes it, row by row."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["video", "frame", "point", "x", "y", "z", "observed", *points.extra])
    for f in range(points.num_frames):
        for p, name in enumerate(points.point_names):
            writer.writerow(
                [
                    points.videos[f],
                    int(points.frames[f]),
                    name,
                    *("" if not math.isfinite(v) else repr(float(v)) for v in points.xyz[f, p]),
                    int(bool(points.observed[f, p])),
                    *(_cell(e[f, p], name in COUNT_COLUMNS) for name, e in points.extra.items()),
                ]
            )
    return buffer.getvalue()


def _cell(value: float, count: bool) -> str:
    """An extra column's cell: counts and 0/1 flags whole (`flag == 1` matches as text), other values by repr."""
    if not math.isfinite(value):
        return ""
    return str(int(value)) if count and value == round(value) else repr(float(value))


def _points(F: int, P: int, seed: int) -> FramePoints:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(F, P, 3)) * 10.0 ** rng.integers(-8, 8, size=(F, P, 3))
    if xyz.size:
        xyz.ravel()[rng.integers(0, xyz.size, 40)] = rng.choice(AWKWARD, 40)
    repeated = np.broadcast_to(rng.choice(AWKWARD, F)[:, None], (F, P))  # one value per frame: formatted once
    return FramePoints(
        videos=[("cam,0", 'cam "1"', "cam 2", "")[f % 4] for f in range(F)],
        frames=np.arange(F) * 7,
        point_names=[f"p{p}" if p % 3 else f"p,{p}" for p in range(P)],
        xyz=xyz,
        observed=rng.random((F, P)) < 0.5,
        extra={
            "repeated": repeated,
            "flag": np.where(rng.random((F, P)) < 0.05, np.nan, (rng.random((F, P)) < 0.1).astype(float)),
            "views": rng.choice([1.0, 2.0, 3.5, -0.0, math.nan], (F, P)),
            "ints": np.ones((F, P), int),
        },
    )


def test_points_text_is_what_csv_writer_writes(tmp_path):
    for F, P, seed in ((0, 3, 0), (1, 1, 1), (9, 4, 2), (300, 41, 3)):
        points = _points(F, P, seed)
        path = write_points(tmp_path / "points3d.csv", points)
        assert path.read_bytes() == _csv_reference(points).encode()


def _sequencing(F: int, seed: int, extra: dict) -> Sequencing:
    rng = np.random.default_rng(seed)
    neighbours = [rng.integers(0, F, int(rng.integers(0, 4))) for _ in range(F)]
    weights = [rng.random(len(n)) * 10.0 ** float(rng.integers(-20, 20)) for n in neighbours]
    if F:
        weights[0] = np.array(AWKWARD)
        neighbours[0] = np.arange(len(AWKWARD)) % F
    return Sequencing(
        videos=[("cam0", 'cäm "1"', "a\\b")[f % 3] for f in range(F)],
        frames=np.arange(F) * 3,
        neighbours=neighbours,
        weights=weights,
        extra=extra,
    )


def test_sequencing_text_is_what_json_dumps_writes(tmp_path):
    extras = ({}, {"clocks": {"offsets": [1.5, math.nan, -0.0], "empty": [], "nested": {"a": {}}, "s": "é"}, "n": 3})
    for F, seed in ((0, 0), (1, 1), (7, 2), (200, 3)):
        for extra in extras:
            sequencing = _sequencing(F, seed, extra)
            expected = {
                "frames": [
                    {
                        "video": sequencing.videos[i],
                        "frame": int(sequencing.frames[i]),
                        "neighbours": [
                            {"video": sequencing.videos[int(j)], "frame": int(sequencing.frames[int(j)]), "weight": w}
                            for j, w in zip(sequencing.neighbours[i], sequencing.weights[i].tolist(), strict=True)
                        ],
                    }
                    for i in range(F)
                ],
                **extra,
            }
            path = write_sequencing(tmp_path / "sequencing.json", sequencing)
            assert path.read_text() == json.dumps(expected, indent=1) + "\n"
