"""Shared low-level readers for the dataset modules.

Everything here turns bad input into a one-line :class:`DatasetError` naming the file (and the line
for text tables) and what is wrong. Readers:

* :func:`read_rgb` — 8-bit (or 16-bit) colour PNG/JPG via OpenCV -> (H, W, 3) float32 RGB in [0, 1].
* :func:`read_depth_png` — 16-bit single-channel PNG depth -> (H, W) float32 metres (value / scale).
* :func:`read_label_png` — 8/16-bit id images (channel 0 when 3-channel); :func:`read_mask_png` —
  8/16-bit motion masks (nonzero in any colour channel = dynamic), optionally size-checked.
* :func:`read_exr_depth` — OpenEXR depth through the ``OpenEXR`` package (HALF or FLOAT channels).
Text tables (trajectories, intrinsics files) are in :mod:`data_modules.tables`.

Writers (:func:`atomic_write`, :func:`write_mask_png`) replace a file all at once.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from data_modules.frame import DatasetError, Intrinsics

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
        OSError: the folder cannot be created or written (full disk, read-only file system, no
            permission); its ``filename`` is ``path`` (never the temporary), so the one-line error
            names the file the user asked for.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise _naming(exc, path) from exc
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
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _naming(exc, path) from exc
        raise
    return path


def _naming(exc: OSError, path: Path) -> OSError:
    """The same OS error (errno and message) with ``path`` as its file name."""
    if exc.errno is None:
        return OSError(f"{path}: {exc}")
    return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))  # the errno picks the subclass


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
