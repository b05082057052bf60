"""Text tables of the dataset formats, with ``file:line`` errors.

* :func:`read_table` — whitespace/comma separated text tables with ``#`` comments and typed columns;
  :func:`read_pose_table` builds on it for ``key tx ty tz qx qy qz qw`` files, and
  :func:`read_tum_trajectory` / :func:`write_tum_trajectory` read and write TUM trajectories
  (the writer replaces the file all at once).
* :func:`read_intrinsics_file` — ``intrinsics.txt`` / ``.json`` of the folder layout and calibration files.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from data_modules.frame import DatasetError, Intrinsics, intrinsics_from
from data_modules.io import atomic_write
from data_modules.poses import matrix_to_quat, pose_from_tq


@dataclass(frozen=True)
class Row:
    """One parsed line of a text table: its 1-based line number and its converted values."""

    lineno: int
    values: tuple


def finite_float(text: str) -> float:
    """``float`` that rejects NaN and inf (used as a column converter)."""
    v = float(text)
    if not math.isfinite(v):
        raise ValueError("not finite")
    return v


def integer(text: str) -> int:
    """``int`` that also accepts integral floats like ``12.0`` (Blender exports)."""
    try:
        return int(text)
    except ValueError:
        v = float(text)
        if not v.is_integer():
            raise ValueError("not an integer") from None
        return int(v)


def read_table(
    path: str | Path,
    columns: Sequence[tuple[str, Callable[[str], object]]],
    *,
    min_columns: int | None = None,
    max_rows: int | None = None,
    allow_extra: bool = False,
    allow_empty: bool = False,
    what: str = "file",
) -> list[Row]:
    """Parse a text table: one record per line, fields split on whitespace and/or commas.

    Blank lines and lines starting with ``#`` are skipped. Every other line must have between
    ``min_columns`` (default: all) and ``len(columns)`` fields (more only with ``allow_extra``), and
    each field must convert with its column's converter.

    Args:
        path: the file.
        columns: ``(name, converter)`` per column, e.g. ``("timestamp", finite_float)``.
        min_columns: fewest fields a line may have (trailing columns optional); default all.
        max_rows: stop after this many records (e.g. 1 for a one-line calibration file).
        allow_extra: ignore fields beyond ``len(columns)`` instead of failing.
        allow_empty: return [] for a file without records instead of failing.
        what: how the file is described in "not found" errors.
    Returns:
        The records in file order.
    Raises:
        DatasetError ``<path>:<line>: <problem>`` for a malformed line; ``<path>: ...`` for a
        missing, unreadable or empty file.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, f"{what} not found")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read {what} as text ({type(e).__name__})") from None
    need = len(columns) if min_columns is None else min_columns
    names = " ".join(n for n, _ in columns)
    rows: list[Row] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) < need or (len(parts) > len(columns) and not allow_extra):
            expect = f"{need}" if need == len(columns) else f"{need} to {len(columns)}"
            raise DatasetError(f"{path}:{lineno}", f"expected {expect} fields ({names}), got {len(parts)}")
        values = []
        for (name, conv), field in zip(columns, parts):
            try:
                values.append(conv(field))
            except (ValueError, TypeError):
                raise DatasetError(f"{path}:{lineno}", f"bad {name} {field!r}") from None
        rows.append(Row(lineno, tuple(values)))
        if max_rows is not None and len(rows) >= max_rows:
            break
    if not rows and not allow_empty:
        raise DatasetError(path, f"{what} has no data lines")
    return rows


POSE_COLUMNS = [(n, finite_float) for n in ("tx", "ty", "tz", "qx", "qy", "qz", "qw")]


def read_pose_table(path: str | Path, key: str = "timestamp", what: str = "trajectory file") -> tuple[np.ndarray, torch.Tensor]:
    """Read ``key tx ty tz qx qy qz qw`` lines (TUM order, quaternion scalar last).

    Args:
        key: ``"timestamp"`` (float seconds, TUM) or ``"frame"`` (integer frame number, Co-Fusion).
        what: how the file is described in errors ("ground-truth file", ...).
    Returns:
        keys (N,) float64 (or int64 for frames) and poses (N, 4, 4) float64 torch tensor.
    Raises:
        DatasetError ``file:line`` for malformed lines, zero quaternions, and duplicate or
        decreasing keys; ``file`` for a missing file or one without poses.
    """
    conv = integer if key == "frame" else finite_float
    rows = read_table(path, [(key, conv), *POSE_COLUMNS], allow_empty=True, what=what)
    if not rows:
        raise DatasetError(path, f"{what} has no poses")
    keys = np.array([r.values[0] for r in rows], dtype=np.int64 if key == "frame" else np.float64)
    vals = np.array([r.values[1:] for r in rows], dtype=np.float64)
    for r, v in zip(rows, vals):
        if np.linalg.norm(v[3:]) < 1e-9:
            raise DatasetError(f"{path}:{r.lineno}", "zero quaternion")
    for j in range(1, len(rows)):
        if keys[j] <= keys[j - 1]:
            raise DatasetError(f"{path}:{rows[j].lineno}", f"{key} {keys[j]} is not after the previous line's {keys[j - 1]}")
    t = torch.from_numpy(vals[:, :3])
    q = torch.from_numpy(vals[:, 3:])
    return keys, pose_from_tq(t, q)


def read_tum_trajectory(path: str | Path, what: str = "trajectory file") -> tuple[np.ndarray, torch.Tensor]:
    """Read a TUM trajectory file ``timestamp tx ty tz qx qy qz qw`` ('#' comments, commas allowed).

    Returns:
        timestamps (N,) float64 strictly increasing [s] and poses (N, 4, 4) float64.
    Raises:
        DatasetError naming the file (and the line) for a missing or empty file or a bad line.
    """
    return read_pose_table(path, key="timestamp", what=what)


def write_tum_trajectory(path: str | Path, timestamps: Sequence[float] | np.ndarray, poses: torch.Tensor) -> Path:
    """Write a TUM trajectory file (atomically, see :func:`atomic_write`).

    Args:
        timestamps: (N,) seconds, written with 6 decimals.
        poses: (N, 4, 4) camera-to-world; translation and quaternion written with 9 decimals.
    Returns:
        ``path`` as a Path.
    Raises:
        ValueError: timestamps and poses differ in length.
    """
    poses = torch.as_tensor(poses, dtype=torch.float64).detach().cpu()
    ts = np.asarray(timestamps, dtype=np.float64)
    if len(ts) != len(poses):
        raise ValueError(f"{len(ts)} timestamps but {len(poses)} poses")
    q = matrix_to_quat(poses[:, :3, :3]).numpy()
    t = poses[:, :3, 3].numpy()
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join([f"{ts[i]:.6f}"] + [f"{v:.9f}" for v in (*t[i], *q[i])]) for i in range(len(ts))]
    return atomic_write(path, "\n".join(lines) + "\n")


def read_intrinsics_file(path: str | Path, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Read intrinsics from ``fx fy cx cy [width height]`` text (first data line) or a JSON object.

    JSON keys: ``fx fy cx cy`` and optional ``width height``. ``width``/``height`` arguments fill in
    a size the file does not give; without either, raise.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        if not path.is_file():
            raise DatasetError(path, "intrinsics file not found")
        try:
            obj = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise DatasetError(path, f"invalid JSON ({e})") from None
        if not isinstance(obj, dict):
            raise DatasetError(path, "expected a JSON object with fx, fy, cx, cy")
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in obj]
        if missing:
            raise DatasetError(path, f"missing key(s) {', '.join(missing)}")
        try:
            vals = [float(obj[k]) for k in ("fx", "fy", "cx", "cy")]
            w = int(obj["width"]) if "width" in obj else None
            h = int(obj["height"]) if "height" in obj else None
        except (TypeError, ValueError):
            raise DatasetError(path, "fx, fy, cx, cy, width, height must be numbers") from None
    else:
        cols = [(n, finite_float) for n in ("fx", "fy", "cx", "cy")] + [("width", integer), ("height", integer)]
        row = read_table(path, cols, min_columns=4, max_rows=1, what="calibration file")[0]
        if len(row.values) == 5:
            raise DatasetError(f"{path}:{row.lineno}", "expected 4 or 6 numbers (fx fy cx cy [width height]), got 5")
        vals = list(row.values[:4])
        w, h = (row.values[4], row.values[5]) if len(row.values) == 6 else (None, None)
    w = w if w is not None else width
    h = h if h is not None else height
    if w is None or h is None:
        raise DatasetError(path, "image size unknown (give width height in the file or the config)")
    return intrinsics_from(path, *vals, w, h)
