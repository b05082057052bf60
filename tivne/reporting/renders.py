"""Frames of a run re-rendered from its checkpoint at their estimated poses, beside what the sensor
saw (the report's render / GT / depth-error contact sheet)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from data_modules.sequence import SequenceView
from data_modules.timestamps import associate_by_timestamp
from tivne.config import RenderConfig
from tivne.field.networks import TimeVaryingField, time_to_tau
from tivne.meshing import field_device
from tivne.render.rays import View
from tivne.render.renderer import render_image


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


@torch.no_grad()
def render_pairs(
    field: TimeVaryingField, meta: dict[str, Any], view: SequenceView, render: RenderConfig, count: int, stride: int
) -> list[FramePair]:
    """Re-render ``count`` evenly spaced processed frames of a run.

    Args:
        field, meta: a loaded checkpoint (``meta``: ``timestamps`` (N,), ``poses`` (N, 4, 4), ``t0``).
        view: the sequence the run processed (frames matched to the checkpoint by timestamp).
    """
    stamps = np.asarray(meta["timestamps"], dtype=np.float64)
    poses = torch.as_tensor(meta["poses"])
    i_run, i_view = associate_by_timestamp(stamps, view.timestamps, 1e-4)
    device = field_device(field)
    K = view.intrinsics.K(device=device)
    pairs = []
    for k in evenly_spaced(len(i_run), count):
        a, b = int(i_run[k]), int(i_view[k])
        frame = view[b]
        tau = time_to_tau(stamps[a], meta["t0"], field.time_scale)
        posed = View(b, tau, frame.rgb.to(device), frame.depth.to(device), None, poses[a].to(device=device, dtype=torch.float32))
        rgb, depth = render_image(field, posed, K, render, stride)
        pairs.append(FramePair(
            frame=b, time_s=float(stamps[a] - stamps[0]),
            observed_rgb=frame.rgb[::stride, ::stride].numpy(), rendered_rgb=rgb.cpu().numpy(),
            observed_depth=frame.depth[::stride, ::stride].numpy(), rendered_depth=depth.cpu().numpy(),
        ))
    return pairs
