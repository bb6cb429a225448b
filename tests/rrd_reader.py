"""Read an .rrd back in tests with `rerun.chunk.RrdReader` (rerun 0.41 has no `rerun.dataframe`).

Entity paths come back with a leading '/'; duration times are returned here as float seconds.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from rerun.chunk import RrdReader


@dataclass(kw_only=True)
class ChunkInfo:
    entity: str  # with the leading '/'
    static: bool
    timelines: list[str]
    num_rows: int
    columns: list[str]


def chunks(path: str | Path) -> list[ChunkInfo]:
    """One entry per chunk of the file (data chunks only; the blueprint lives in another store)."""
    out = []
    for chunk in RrdReader(Path(path)).stream().to_chunks():
        batch = chunk.to_record_batch()
        out.append(
            ChunkInfo(
                entity=chunk.entity_path,
                static=chunk.is_static,
                timelines=list(chunk.timeline_names),
                num_rows=chunk.num_rows,
                columns=list(batch.schema.names),
            )
        )
    return out


def entities(path: str | Path) -> set[str]:
    return {c.entity for c in chunks(path)}


def timelines(path: str | Path) -> set[str]:
    return {name for c in chunks(path) for name in c.timelines}


def _times(column: pa.Array) -> list[Any]:
    """Time values as Python numbers: sequences as int, durations as float seconds (ns precision kept)."""
    if pa.types.is_duration(column.type):
        # to_pylist() would make datetime.timedelta, which refuses nanoseconds without pandas.
        unit = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}[column.type.unit]
        return [None if v is None else v * unit for v in column.cast(pa.int64()).to_pylist()]
    return column.to_pylist()


def component_rows(path: str | Path, entity: str, component: str, timeline: str) -> dict[Any, Any]:
    """{time on `timeline`: value of `component`} for the temporal rows of `entity`.

    Values are numpy arrays for numeric lists, plain Python values otherwise (e.g. list[str] for labels).
    Duration times come back as float seconds.
    """
    out: dict[Any, Any] = {}
    for chunk in RrdReader(Path(path)).stream().to_chunks():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names or timeline not in batch.schema.names:
            continue
        for t, v in zip(_times(batch.column(timeline)), batch.column(component).to_pylist(), strict=True):
            if v is None or t is None:
                continue
            out[t] = v if v and isinstance(_first(v), str) else np.array(v)
    return out


def static_component(path: str | Path, entity: str, component: str) -> Any:
    """The last static value of `component` on `entity` (None when absent)."""
    value = None
    for chunk in RrdReader(Path(path)).stream().to_chunks():
        if chunk.entity_path != entity or not chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if component in batch.schema.names:
            for v in batch.column(component).to_pylist():
                if v is not None:
                    value = v
    return value


def _first(value: Any) -> Any:
    while isinstance(value, list) and value:
        value = value[0]
    return value


def blueprint_views(path: str | Path) -> list[tuple[str, str]]:
    """(display name, space origin) of every view in the file's blueprint ([] without a blueprint)."""
    reader = RrdReader(Path(path))
    views = []
    for store in reader.blueprints():
        for chunk in reader.stream(store=store).to_chunks():
            batch = chunk.to_record_batch()
            names = batch.schema.names
            if "ViewBlueprint:space_origin" not in names:
                continue
            origins = batch.column("ViewBlueprint:space_origin").to_pylist()
            titles = (
                batch.column("ViewBlueprint:display_name").to_pylist()
                if "ViewBlueprint:display_name" in names
                else [None] * len(origins)
            )
            for title, origin in zip(titles, origins, strict=True):
                if origin is not None:
                    views.append((_first(title) or "", _first(origin)))
    return views


def verify(path: str | Path) -> subprocess.CompletedProcess:
    """Run `rerun rrd verify PATH` (the CLI shipped with rerun-sdk), falling back to `python -m rerun`."""
    exe = shutil.which("rerun")
    command = [exe] if exe else [sys.executable, "-m", "rerun"]
    return subprocess.run(
        [*command, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120, check=False
    )
