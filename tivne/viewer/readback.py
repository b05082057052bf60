"""A recording read back with rerun's own reader (``rerun.chunk.RrdReader``): the rows of each entity
with their ``frame`` and ``scene_time`` and their components as plain values (tests, checks)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tivne.viewer.entities import rerun

TIMELINES = ("frame", "scene_time", "log_time")


@dataclass(frozen=True)
class Row:
    """One logged row: frame number (None: static), seconds since the first frame (None: static),
    component -> value (``"Transform3D:translation"`` -> [[x, y, z]])."""

    frame: int | None
    scene_time: float | None
    values: dict[str, Any]


def read_recording(path: str | Path) -> dict[str, list[Row]]:
    """{entity path: rows sorted by (frame, scene_time)} of the first recording in an .rrd file."""
    rerun()  # the one-line ImportError when the extra is missing
    from rerun.chunk import RrdReader

    rows: dict[str, list[Row]] = defaultdict(list)
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if not n.startswith("rerun.controls") and n not in TIMELINES]
        columns = {n: batch.column(n).to_pylist() for n in names}
        frames = batch.column("frame").to_pylist() if "frame" in batch.schema.names else [None] * batch.num_rows
        times = batch.column("scene_time").to_pylist() if "scene_time" in batch.schema.names else [None] * batch.num_rows
        for i in range(batch.num_rows):
            t = times[i]
            seconds = None if t is None else t.total_seconds() if hasattr(t, "total_seconds") else float(t) / 1e9
            rows[chunk.entity_path].append(Row(frames[i], seconds, {n: columns[n][i] for n in names if columns[n][i] is not None}))
    for entity in rows:
        rows[entity].sort(key=lambda r: (-1 if r.frame is None else r.frame, r.scene_time or 0.0))
    return dict(rows)


def rows_with(rows: list[Row], component: str) -> list[Row]:
    """The rows that carry ``component``."""
    return [r for r in rows if component in r.values]


def pose_of(row: Row) -> np.ndarray:
    """(4, 4) c2w from a row with ``Transform3D:translation`` and ``Transform3D:mat3x3`` (column-major, as rerun stores it)."""
    pose = np.eye(4)
    pose[:3, 3] = np.asarray(row.values["Transform3D:translation"][0], dtype=np.float64)
    pose[:3, :3] = np.asarray(row.values["Transform3D:mat3x3"][0], dtype=np.float64).reshape(3, 3).T
    return pose


def mesh_of(row: Row) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) faces of a ``Mesh3D`` row."""
    verts = np.asarray(row.values["Mesh3D:vertex_positions"], dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(row.values["Mesh3D:triangle_indices"], dtype=np.int64).reshape(-1, 3)
    return verts, faces
