"""On-disk cache of rendered synthetic frames, one folder per render configuration.

``<root>/<prefix>-<key>/frame_NNNNN.npz`` holds ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32
metres and ``labels`` (H, W) uint8 object ids (0 = static); ``params.json`` beside them records what the
key hashes. Files are written atomically (:func:`data_modules.io.atomic_write`) and stored
uncompressed: sensor noise makes them nearly incompressible, and zlib would cost more than a render.
Any unreadable, truncated or mismatched file counts as a miss and is rendered again.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import warnings
from pathlib import Path

import numpy as np

from data_modules.io import atomic_write

__all__ = ["FrameCache", "render_key"]


def render_key(params: dict[str, object]) -> str:
    """Short stable hash (12 hex digits) of JSON-serialisable render parameters."""
    text = json.dumps(params, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


class FrameCache:
    """Frames of one render configuration under ``root`` (None = no caching: every read misses).

    Args:
        root: cache directory (``~`` expanded) or None.
        prefix: folder name prefix (the scene name).
        params: every parameter that determines the pixels, including a version.
    """

    def __init__(self, root: str | os.PathLike | None, prefix: str, params: dict[str, object]) -> None:
        self.params = params
        self.key = render_key(params)
        self.folder: Path | None = None
        if root is not None and str(root) != "":
            self.folder = Path(os.path.expanduser(str(root))) / f"{prefix}-{self.key}"
        self._warned = False

    def path(self, i: int) -> Path | None:
        return None if self.folder is None else self.folder / f"frame_{i:05d}.npz"

    def read(self, i: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(rgb uint8 (H, W, 3), depth float32 (H, W), labels uint8 (H, W)) of frame ``i``, or None."""
        path = self.path(i)
        if path is None or not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                rgb, depth, labels = z["rgb"], z["depth"], z["labels"]
        except Exception:  # noqa: BLE001 -- any unreadable / truncated / foreign file is re-rendered
            return None
        expected = (((height, width, 3), np.uint8), ((height, width), np.float32), ((height, width), np.uint8))
        for arr, (shape, dtype) in zip((rgb, depth, labels), expected):
            if arr.shape != shape or arr.dtype != dtype:
                return None
        return rgb, depth, labels

    def write(self, i: int, rgb: np.ndarray, depth: np.ndarray, labels: np.ndarray) -> None:
        """Store frame ``i``; a cache that cannot be written warns once and is then left alone."""
        path = self.path(i)
        if path is None:
            return
        try:
            params = path.parent / "params.json"
            if not params.exists():
                atomic_write(params, json.dumps(self.params, indent=1, sort_keys=True, default=str))
            buf = io.BytesIO()
            np.savez(buf, rgb=rgb, depth=depth, labels=labels)
            atomic_write(path, buf.getvalue())
        except OSError as exc:
            if not self._warned:
                warnings.warn(f"{path.parent}: cannot write the frame cache ({exc}); rendering without it")
                self._warned = True
