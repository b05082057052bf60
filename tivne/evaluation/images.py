"""Image metrics of re-rendered frames: the field rendered at processed frames' estimated poses, at
the frame's own time, against the observed colour (:mod:`tivne.metrics.image`).

Rendering is depth-guided (:func:`tivne.render.renderer.render_image` places the samples around the
observed depth, as in tracking and mapping), so only pixels with observed depth are rendered and
compared; geometry errors show only through the colour the field gives near the observed depth.
Pixels without depth are set to 0 in both images, so SSIM windows at their border compare like with
like.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from data_modules.sequence import SequenceView
from data_modules.timestamps import associate_by_timestamp
from tivne.config import RenderConfig
from tivne.field.networks import TimeVaryingField
from tivne.meshing import field_device
from tivne.metrics.image import lpips, mse, psnr, ssim
from tivne.render.rays import View
from tivne.render.renderer import render_image

IMAGE_KEYS = ("psnr_db", "ssim", "mse", "lpips", "psnr_dynamic_db", "psnr_frames")


@dataclass(frozen=True)
class RenderedFrame:
    """One re-rendered frame at the evaluation resolution (every ``stride``-th pixel).

    rgb: (H, W, 3) rendered colour; observed: (H, W, 3) observed colour, both in [0, 1];
    valid: (H, W) bool, observed depth (the rendered pixels); dynamic: (H, W) bool motion mask or None.
    """

    rgb: torch.Tensor
    observed: torch.Tensor
    valid: torch.Tensor
    dynamic: torch.Tensor | None = None


@dataclass
class Rerendered:
    """One processed frame re-rendered at its estimated pose: ``run_index`` into the checkpoint's
    records, the dataset ``frame`` it was matched to (by timestamp), and (H', W', 3) rgb / (H', W')
    depth at the pixel stride."""

    run_index: int
    view_index: int
    frame: Any
    rgb: torch.Tensor
    depth: torch.Tensor


@torch.no_grad()
def rerender_processed(
    field: TimeVaryingField,
    meta: dict[str, Any],
    view: SequenceView,
    render: RenderConfig,
    pick: Callable[[int], Sequence[int]],
    stride: int = 1,
) -> list[Rerendered]:
    """Re-render the processed frames ``pick(n)`` chooses among the n matched ones.

    Args:
        field, meta: a loaded checkpoint (``meta``: ``timestamps`` (N,), ``poses`` (N, 4, 4) c2w, ``clock``).
        view: the sequence the run processed (frames are matched to the checkpoint by timestamp).
        pick: n -> positions in range(n) to render; stride: pixel step.
    Returns:
        the re-rendered frames, rgb and depth on the CPU.
    """
    stamps = np.asarray(meta["timestamps"], dtype=np.float64)
    poses = torch.as_tensor(meta["poses"])
    i_run, i_view = associate_by_timestamp(stamps, view.timestamps, 1e-4)
    device = field_device(field)
    K = view.intrinsics.K(device=device)
    out = []
    for k in pick(len(i_run)):
        a, b = int(i_run[k]), int(i_view[k])
        frame = view[b]
        tau = meta["clock"].tau(stamps[a])
        posed = View(b, tau, frame.rgb.to(device), frame.depth.to(device), None, poses[a].to(device=device, dtype=torch.float32))
        rgb, depth = render_image(field, posed, K, render, stride)
        out.append(Rerendered(a, b, frame, rgb.cpu(), depth.cpu()))
    return out


def render_frames(
    field: TimeVaryingField,
    meta: dict[str, Any],
    view: SequenceView,
    render: RenderConfig,
    every: int,
    stride: int = 1,
) -> list[RenderedFrame]:
    """Render every ``every``-th processed frame of a run at its estimated pose (see
    :func:`rerender_processed`); the observed colour, depth validity and mask at the same stride."""
    frames = []
    for r in rerender_processed(field, meta, view, render, lambda n: range(0, n, max(1, int(every))), stride):
        f = r.frame
        dynamic = None if f.mask is None else f.mask[::stride, ::stride]
        frames.append(RenderedFrame(r.rgb, f.rgb[::stride, ::stride], f.depth[::stride, ::stride] > 0, dynamic))
    return frames


def null_images(reason: str) -> dict[str, Any]:
    """Every image value null, each with its ``*_reason`` (``psnr_db`` -> ``psnr_reason``)."""
    out: dict[str, Any] = {"psnr_frames": 0}
    for key in IMAGE_KEYS[:-1]:
        out[key] = None
        out[key.removesuffix("_db") + "_reason"] = reason
    return out


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def image_metrics(frames: Sequence[RenderedFrame]) -> dict[str, Any]:
    """PSNR / SSIM / MSE / LPIPS over the frames' pixels with observed depth.

    Returns:
        ``psnr_db`` (mean of the frames' PSNRs), ``ssim``, ``mse``, ``lpips`` (None offline, with
        ``lpips_reason``), ``psnr_dynamic_db`` (PSNR over moving-object pixels, frames with a motion
        mask), ``psnr_frames``; None with ``psnr_reason`` when no frame has a pixel with depth.
    """
    used = [f for f in frames if bool(f.valid.any())]
    if not used:
        return null_images("no re-rendered frame has a pixel with depth")
    valid = torch.stack([f.valid for f in used])  # (B, H, W)
    keep = valid[..., None].float()
    pred = (torch.stack([f.rgb for f in used]).float() * keep).permute(0, 3, 1, 2)  # (B, 3, H, W)
    obs = (torch.stack([f.observed for f in used]).float() * keep).permute(0, 3, 1, 2)
    out: dict[str, Any] = {
        "psnr_db": _finite(psnr(pred, obs, valid)),
        "ssim": _finite(ssim(pred, obs, valid)),
        "mse": _finite(mse(pred, obs, valid)),
        "psnr_frames": len(used),
    }
    try:
        out["lpips"], reason = lpips(pred, obs)
    except RuntimeError as exc:  # e.g. images smaller than the backbone's receptive field
        out["lpips"], reason = None, f"LPIPS failed ({str(exc).splitlines()[0]})"
    if reason:
        out["lpips_reason"] = reason
    moving = [i for i, f in enumerate(used) if f.dynamic is not None and bool((f.dynamic & f.valid).any())]
    if moving:
        masks = torch.stack([used[i].dynamic & used[i].valid for i in moving])
        out["psnr_dynamic_db"] = _finite(psnr(pred[moving], obs[moving], masks))
    else:
        out["psnr_dynamic_db"] = None
        out["psnr_dynamic_reason"] = "no re-rendered frame shows a moving object (or the frames have no motion mask)"
    return out
