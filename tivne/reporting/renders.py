"""Frames of a run re-rendered from its checkpoint at their estimated poses, beside what the sensor
saw (the report's render / GT / depth-error contact sheet)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from data_modules.sequence import SequenceView
from tivne.config import RenderConfig
from tivne.evaluation.images import rerender_processed
from tivne.field.networks import TimeVaryingField


@dataclass(frozen=True)
class FramePair:
    """One frame at every ``stride``-th pixel: observed and rendered colour (H, W, 3) in [0, 1] and
    depth (H, W) metres (0 = none; the renderer only renders pixels with observed depth)."""

    frame: int
    time_s: float
    observed_rgb: np.ndarray
    rendered_rgb: np.ndarray
    observed_depth: np.ndarray
    rendered_depth: np.ndarray


def evenly_spaced(n: int, count: int) -> list[int]:
    """``count`` indices spread over range(n), first and last included (fewer when n is small)."""
    if n <= 0 or count <= 0:
        return []
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(count, n))})


def render_pairs(
    field: TimeVaryingField, meta: dict[str, Any], view: SequenceView, render: RenderConfig, count: int, stride: int
) -> list[FramePair]:
    """Re-render ``count`` evenly spaced processed frames of a run.

    Args:
        field, meta: a loaded checkpoint (``meta``: ``timestamps`` (N,), ``poses`` (N, 4, 4), ``clock``).
        view: the sequence the run processed (frames matched to the checkpoint by timestamp).
    """
    stamps = np.asarray(meta["timestamps"], dtype=np.float64)
    return [
        FramePair(
            frame=r.view_index, time_s=float(stamps[r.run_index] - stamps[0]),
            observed_rgb=r.frame.rgb[::stride, ::stride].numpy(), rendered_rgb=r.rgb.numpy(),
            observed_depth=r.frame.depth[::stride, ::stride].numpy(), rendered_depth=r.depth.numpy(),
        )
        for r in rerender_processed(field, meta, view, render, lambda n: evenly_spaced(n, count), stride)
    ]
