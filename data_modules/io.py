"""Shared low-level readers for the dataset modules.

Everything here turns bad input into a one-line :class:`DatasetError` naming the file (and the line
for text tables) and what is wrong. Readers:

* :func:`read_rgb` — 8-bit (or 16-bit) colour PNG/JPG via OpenCV -> (H, W, 3) float32 RGB in [0, 1].
* :func:`read_depth_png` — 16-bit single-channel PNG depth -> (H, W) float32 metres (value / scale).
* :func:`read_label_png` — 8/16-bit id images (channel 0 when 3-channel); :func:`read_mask_png` —
  8/16-bit motion masks (nonzero in any colour channel = dynamic), optionally size-checked.
* :func:`read_exr_depth` — OpenEXR depth through the ``OpenEXR`` package (HALF or FLOAT channels).
* :func:`read_table` — whitespace/comma separated text tables with ``#`` comments, typed columns and
  ``file:line`` errors; :func:`read_pose_table` builds on it for ``key tx ty tz qx qy qz qw`` files
  and :func:`read_tum_trajectory` / :func:`write_tum_trajectory` read and write TUM trajectories.

Writers (:func:`atomic_write`, :func:`write_mask_png`, :func:`write_tum_trajectory`) replace a file
all at once.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from data_modules.frame import DatasetError, Intrinsics, intrinsics_from
from data_modules.poses import matrix_to_quat, pose_from_tq

# --------------------------------------------------------------------------------------- writes


def atomic_write(path: str | Path, data: bytes | str | Callable[[Path], None]) -> Path:
    """Write ``path`` all at once: a temporary file in the same folder, then a rename.

    A reader sees the old content or the new, never half a file, and a failed write (full disk,
    an exception while serialising) leaves the old file untouched and no temporary file behind.

    Args:
        data: the bytes or text to write, or a callable that writes the file at the path it is given
            (for writers that want a file name, such as ``torch.save`` or ``trimesh.export``).
    Returns:
        ``path`` as a Path.
    Raises:
        OSError: the folder cannot be created or written (the message names the path).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(name)
    try:
        if callable(data):
            os.close(fd)
            data(tmp)
        else:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data.encode() if isinstance(data, str) else data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# --------------------------------------------------------------------------------------- paths


def require_dir(path: str | Path, what: str = "folder") -> Path:
    """Return ``path`` as a Path; raise DatasetError naming it unless it is an existing directory."""
    if path is None or str(path) in ("", "???"):
        raise DatasetError(f"{what}", "no path given (set dataset.root=...)")
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(p, f"{what} not found")
    if not p.is_dir():
        raise DatasetError(p, f"{what} is not a directory")
    return p


def require_file(path: str | Path, what: str = "file") -> Path:
    """Return ``path`` as a Path; raise DatasetError naming it unless it is an existing regular file."""
    if path is None or str(path) in ("", "???"):
        raise DatasetError(f"{what}", "no path given (set dataset.root=...)")
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(p, f"{what} not found")
    if not p.is_file():
        raise DatasetError(p, f"{what} is not a regular file")
    return p


# -------------------------------------------------------------------------------------- images

# OpenCV prints "[ WARN:0@...] ..." lines for a truncated or corrupt file on top of returning None,
# which the readers already turn into one-line errors naming the file: keep only OpenCV's errors.
with contextlib.suppress(AttributeError):  # builds without the utils.logging bindings
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(path, "image file not found")
    # np.fromfile + imdecode works for any path encoding.
    try:
        buf = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        raise DatasetError(path, f"cannot read file ({e.strerror or e})") from None
    if buf.size == 0:
        raise DatasetError(path, "image file is empty")
    img = cv2.imdecode(buf, flags)
    if img is None:
        raise DatasetError(path, "cannot decode image (not a valid PNG/JPEG file?)")
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    """Colour image -> (H, W, 3) float32 RGB in [0, 1].

    Accepts 8- or 16-bit, gray, BGR or BGRA files (alpha dropped, gray replicated).
    """
    path = Path(path)
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise DatasetError(path, f"unsupported colour image type {img.dtype} (expected 8- or 16-bit)")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    else:
        raise DatasetError(path, f"colour image has {img.shape[2]} channels (expected 1, 3 or 4)")
    return img.astype(np.float32) / np.float32(scale)


def read_depth_png(path: str | Path, scale: float) -> np.ndarray:
    """16-bit single-channel depth PNG -> (H, W) float32 metres (raw value / ``scale``; 0 stays 0)."""
    path = Path(path)
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.ndim == 3:
        raise DatasetError(path, f"depth image has {img.shape[2]} channels (expected a single-channel 16-bit PNG)")
    if img.dtype != np.uint16:
        raise DatasetError(path, f"depth image is {img.dtype}, expected 16-bit (uint16) values")
    return (img.astype(np.float32) / np.float32(scale)).astype(np.float32)


def _read_label_image(path: Path) -> np.ndarray:
    """An 8- or 16-bit label image as stored: (H, W) or (H, W, C) in OpenCV channel order."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    if img.dtype not in (np.uint8, np.uint16):
        raise DatasetError(path, f"mask image is {img.dtype}, expected 8- or 16-bit")
    return img


def read_label_png(path: str | Path) -> np.ndarray:
    """Label / id image (8- or 16-bit; channel 0 when it has several) -> (H, W) integer array."""
    img = _read_label_image(Path(path))
    if img.ndim == 3:
        img = img[:, :, 0]  # id masks stored as 3 identical channels; OpenCV order does not matter then
    return img


def read_mask_png(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Motion-mask image -> (H, W) bool, True where the value is nonzero (dynamic).

    A colour mask is dynamic where any colour channel is nonzero (a red-on-black mask has an empty
    OpenCV channel 0); an alpha channel is ignored (it is often 255 everywhere).

    Args:
        size: (width, height) the mask must have, e.g. its frame's; None = any.
    Raises:
        DatasetError naming the file: unreadable, not 8/16-bit, or not ``size``.
    """
    path = Path(path)
    img = _read_label_image(path)
    mask = (img[:, :, :3] != 0).any(axis=2) if img.ndim == 3 else img != 0
    if size is not None and (mask.shape[1], mask.shape[0]) != tuple(size):
        raise DatasetError(path, f"mask is {mask.shape[1]}x{mask.shape[0]} but the frame is {size[0]}x{size[1]}")
    return mask


def write_mask_png(path: str | Path, mask: np.ndarray | torch.Tensor) -> Path:
    """Write an (H, W) bool mask as an 8-bit single-channel PNG (255 = dynamic), atomically
    (:func:`atomic_write`); :func:`read_mask_png` reads it back.

    Returns:
        ``path`` as a Path.
    Raises:
        OSError: the PNG cannot be encoded or written (the message names the path).
    """
    path = Path(path)
    arr = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    ok, buf = cv2.imencode(".png", arr.astype(bool).astype(np.uint8) * np.uint8(255))
    if not ok:
        raise OSError(f"{path}: could not encode the mask as PNG")
    return atomic_write(path, buf.tobytes())


def read_exr_depth(path: str | Path) -> np.ndarray:
    """Read a depth EXR with the ``OpenEXR`` package -> (H, W) float32 (values as stored).

    Channel choice: ``Y``, else ``R`` (then ``G``, ``B``), else ``Z``, else ``depth``/``D``, else the
    only channel. HALF and FLOAT channels are accepted; anything else is an error naming the file.
    """
    import OpenEXR  # local import: only needed for EXR datasets

    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "EXR file not found")
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        channels = f.channels()
    except Exception as e:  # OpenEXR raises RuntimeError with a multi-line message
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise DatasetError(path, f"cannot read EXR file ({msg})") from None
    names = list(channels)
    chosen = None
    for cand in ("Y", "R", "G", "B", "Z", "depth", "D"):
        if cand in channels:
            chosen = cand
            break
    if chosen is None:
        # tolerate layer prefixes such as "ViewLayer.Depth.Z"
        for cand in ("Y", "R", "Z", "depth", "Depth", "D"):
            hits = [n for n in names if n.split(".")[-1] == cand]
            if hits:
                chosen = hits[0]
                break
    if chosen is None and len(names) == 1:
        chosen = names[0]
    if chosen is None:
        raise DatasetError(path, f"no usable depth channel (have {names or 'none'}; expected Y, R, Z or a single channel)")
    pix = np.asarray(channels[chosen].pixels)
    if pix.dtype not in (np.float16, np.float32, np.float64):
        raise DatasetError(path, f"channel {chosen!r} has type {pix.dtype}, expected HALF or FLOAT")
    if pix.ndim != 2:
        raise DatasetError(path, f"channel {chosen!r} has shape {pix.shape}, expected (H, W)")
    return pix.astype(np.float32)


def sanitize_depth(depth: np.ndarray, max_valid: float = 100.0) -> np.ndarray:
    """Map NaN, +-inf, values <= 0 and values > ``max_valid`` metres to 0 (invalid); float32 out."""
    d = np.asarray(depth, dtype=np.float32)
    bad = ~np.isfinite(d) | (d <= 0) | (d > max_valid)
    if bad.any():
        d = np.where(bad, np.float32(0), d).astype(np.float32)
    return d


def check_same_size(rgb: np.ndarray, depth: np.ndarray, rgb_path: Path, depth_path: Path) -> None:
    """Raise naming the depth file when colour and depth images differ in size."""
    if rgb.shape[:2] != depth.shape[:2]:
        raise DatasetError(
            depth_path,
            f"depth is {depth.shape[1]}x{depth.shape[0]} but colour {Path(rgb_path).name} is {rgb.shape[1]}x{rgb.shape[0]}",
        )


def check_size(img: np.ndarray, intr: Intrinsics, path: Path, what: str = "image") -> None:
    """Raise naming ``path`` when the image size differs from the intrinsics' size."""
    h, w = img.shape[:2]
    if (w, h) != (intr.width, intr.height):
        raise DatasetError(path, f"{what} is {w}x{h} but the sequence is {intr.width}x{intr.height}")


# ---------------------------------------------------------------------------------- text tables


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
