"""Masks from a folder of PNGs, one per frame (nonzero = dynamic), and the PNG reader/writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from data_modules.frame import DatasetError, Frame
from data_modules.io import atomic_write
from tivne.masks.base import MaskContext, MaskProvider




def mask_file_name(index: int) -> str:
    """The file name :mod:`tivne.make_masks` writes for frame ``index`` (e.g. ``000123.png``)."""
    return f"{index:06d}.png"


def read_mask_png(path: str | Path, size: tuple[int, int] | None = None) -> torch.Tensor:
    """Read a mask PNG (nonzero = dynamic) as (H, W) bool; ``size`` = (width, height) to check.

    Raises :class:`DatasetError` (one line naming the file) when it is unreadable or the wrong size.
    """
    import cv2

    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(path, "mask is not a readable image")
    if img.ndim == 3:
        img = img.max(axis=2)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise DatasetError(path, f"mask is {img.shape[1]}x{img.shape[0]} but the frame is {size[0]}x{size[1]}")
    return torch.from_numpy(np.ascontiguousarray(img != 0))


def write_mask_png(path: str | Path, mask: torch.Tensor | np.ndarray) -> None:
    """Write an (H, W) bool mask as an 8-bit PNG (255 = dynamic), atomically (tmp file + rename)."""
    import cv2

    path = Path(path)
    arr = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    ok, buf = cv2.imencode(".png", (arr.astype(bool) * 255).astype(np.uint8))
    if not ok:
        raise OSError(f"{path}: could not encode the mask")
    atomic_write(path, buf.tobytes())


class FolderMasks(MaskProvider):
    """Masks from a folder of PNGs (nonzero = dynamic), one per frame.

    ``match='index'``: ``<root>/<index:06d>.png`` (what ``python -m tivne.make_masks`` writes; also
    accepts any zero padding, e.g. ``123.png``). ``match='stem'``: the frame's source file stem, taken
    from ``frame.name`` / ``frame.path`` / ``frame.source`` when the reader sets one, else the index.
    ``missing='error'`` raises a one-line :class:`DatasetError` naming the file; ``'none'`` gives None.
    """

    name = "folder"

    def __init__(self, root: str, match: str = "index", missing: str = "error", suffix: str = ".png") -> None:
        if match not in ("index", "stem"):
            raise ValueError(f"masks.match must be 'index' or 'stem', got {match!r}")
        if missing not in ("error", "none"):
            raise ValueError(f"masks.missing must be 'error' or 'none', got {missing!r}")
        self.root = Path(str(root)).expanduser()
        if not self.root.is_dir():
            raise DatasetError(self.root, "mask folder not found")
        self.match = match
        self.missing = missing
        self.suffix = suffix
        self._by_stem: dict[str, Path] | None = None

    def _stems(self) -> dict[str, Path]:
        if self._by_stem is None:
            self._by_stem = {p.stem: p for p in sorted(self.root.iterdir()) if p.suffix.lower() == self.suffix}
        return self._by_stem

    def path_for(self, frame: Frame) -> Path:
        stems = self._stems()
        if self.match == "stem":
            for attr in ("name", "path", "source", "rgb_path"):
                value = getattr(frame, attr, None)
                if value:
                    stem = Path(str(value)).stem
                    if stem in stems:
                        return stems[stem]
        exact = self.root / mask_file_name(frame.index)
        if exact.exists():
            return exact
        for stem, path in stems.items():  # other zero paddings
            if stem.isdigit() and int(stem) == frame.index:
                return path
        return exact

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        path = self.path_for(frame)
        if not path.is_file():
            if self.missing == "none":
                return None
            raise DatasetError(path, f"mask for frame {frame.index} not found")
        return read_mask_png(path, (frame.width, frame.height)).to(frame.depth.device)


