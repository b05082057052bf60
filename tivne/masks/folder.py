"""Masks from a folder of PNGs, one per frame (nonzero = dynamic); the PNGs are read and written by
:func:`data_modules.io.read_mask_png` / :func:`data_modules.io.write_mask_png`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from data_modules.frame import DatasetError, Frame
from data_modules.io import read_mask_png
from tivne.masks.base import MaskContext, MaskProvider
from tivne.masks.settings import FolderMasksConfig


def mask_file_name(index: int) -> str:
    """The file name :mod:`tivne.make_masks` writes for frame ``index`` (e.g. ``000123.png``)."""
    return f"{index:06d}.png"


class FolderMasks(MaskProvider):
    """Masks from a folder of PNGs (nonzero = dynamic), one per frame.

    ``match='index'``: ``<root>/<index:06d>.png`` (what ``python -m tivne.make_masks`` writes; also
    accepts any zero padding, e.g. ``123.png``). ``match='stem'``: ``<root>/<stem>.png`` with the stem
    of the colour image the frame was read from (``Frame.source``); a frame without one (a KLG log,
    the synthetic cube) is a one-line :class:`DatasetError`, never a silent fall back to the index.
    ``missing='error'`` raises a one-line :class:`DatasetError` naming the file; ``'none'`` gives None.
    """

    name = "folder"

    def __init__(self, **settings: Any) -> None:
        """``settings``: :class:`tivne.masks.settings.FolderMasksConfig` keys (checked there)."""
        cfg = FolderMasksConfig(**settings)
        match, missing, suffix = cfg.match, cfg.missing, cfg.suffix
        self.root = Path(str(cfg.root)).expanduser()
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
        """The mask file of ``frame`` (it may not exist)."""
        stems = self._stems()
        if self.match == "stem":
            if frame.source is None:
                raise DatasetError(
                    "masks.match",
                    f"'stem' needs the file each frame was read from, but frame {frame.index} has none"
                    " (its dataset has no file per frame); use match=index",
                )
            stem = Path(frame.source).stem
            return stems.get(stem, self.root / f"{stem}{self.suffix}")
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
        mask = read_mask_png(path, (frame.width, frame.height))
        return torch.from_numpy(mask).to(frame.depth.device)
