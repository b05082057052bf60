"""Shared scenes of the mask tests: frames, squares and depth images of a plane with objects.

Imported by the test modules here (and tests/tivne/test_make_masks.py) with this folder on sys.path.
"""

from __future__ import annotations

from pathlib import Path

import torch

from data_modules.frame import Frame
from tivne.geometry import backproject, pixel_grid

CONF = Path(__file__).resolve().parents[3] / "conf"
H, W = 48, 64


def make_frame(index: int = 0, mask: torch.Tensor | None = None, depth: torch.Tensor | None = None) -> Frame:
    depth = torch.full((H, W), 2.0) if depth is None else depth
    return Frame(index=index, timestamp=index / 30.0, rgb=torch.full((H, W, 3), 0.5), depth=depth, mask=mask)


def square(y0: int, x0: int, size: int, h: int = H, w: int = W) -> torch.Tensor:
    m = torch.zeros(h, w, dtype=torch.bool)
    m[y0 : y0 + size, x0 : x0 + size] = True
    return m


def scene_depth(obj: torch.Tensor | None, background: float = 3.0, obj_depth: float = 1.5) -> torch.Tensor:
    """Tilted background plane plus an optional fronto-parallel object."""
    y = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    d = background + 0.01 * y
    if obj is not None:
        d = torch.where(obj, torch.full_like(d, obj_depth), d)
    return d


def box_depth(K: torch.Tensor, x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Observed depth of a fronto-parallel square at depth z in front of the z = 3 plane, and its (H, W) pixels."""
    x, y, _ = backproject(pixel_grid(H, W), torch.full((H, W), z), K).unbind(-1)
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return torch.where(inside, torch.full((H, W), z), torch.full((H, W), 3.0)), inside
