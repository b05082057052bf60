"""PSNR / SSIM of re-rendered frames (tivne.evaluation.images) on frames with known errors."""

from __future__ import annotations

import math

import pytest
import torch

from tivne.evaluation.images import RenderedFrame, image_metrics


def frame(error: float, seed: int, dynamic_error: float | None = None) -> RenderedFrame:
    """A 24x32 frame whose left half has depth: rendered = observed + ``error`` there, 0 elsewhere
    (as render_image leaves pixels without depth); a moving object in rows 8-15 of the left half
    is off by ``dynamic_error`` instead."""
    observed = torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(seed)) * 0.5
    valid = torch.zeros(24, 32, dtype=torch.bool)
    valid[:, :16] = True
    rgb = torch.where(valid[..., None], observed + error, torch.zeros(()))
    dynamic = None
    if dynamic_error is not None:
        dynamic = torch.zeros_like(valid)
        dynamic[8:16, :] = True
        rgb[8:16, :16] = observed[8:16, :16] + dynamic_error
    return RenderedFrame(rgb, observed, valid, dynamic)


def test_only_pixels_with_depth_count():
    m = image_metrics([frame(0.1, seed=0), frame(0.1, seed=1)])
    assert m["psnr_db"] == pytest.approx(20.0, abs=1e-4)  # MSE 0.01; the black half without depth would lower it
    assert m["mse"] == pytest.approx(0.01, rel=1e-4) and m["psnr_frames"] == 2
    assert m["psnr_dynamic_db"] is None and "motion mask" in m["psnr_dynamic_reason"]
    exact = image_metrics([frame(0.0, seed=2)])
    assert exact["ssim"] == pytest.approx(1.0, abs=1e-6) and exact["mse"] == 0.0
    assert exact["psnr_db"] is None  # +inf: not a JSON number
    assert m["ssim"] < exact["ssim"]
    assert m["lpips"] is None or math.isfinite(m["lpips"])
    assert m["lpips"] is not None or m["lpips_reason"]


def test_psnr_of_moving_pixels():
    m = image_metrics([frame(0.1, seed=0, dynamic_error=0.2), frame(0.1, seed=3)])
    assert m["psnr_dynamic_db"] == pytest.approx(10 * math.log10(1 / 0.04), abs=1e-4)  # only the frame with a mask
    assert m["psnr_db"] < 20.0


def test_no_pixel_with_depth_is_a_reason():
    empty = RenderedFrame(torch.zeros(4, 4, 3), torch.ones(4, 4, 3), torch.zeros(4, 4, dtype=torch.bool))
    m = image_metrics([empty])
    assert m["psnr_db"] is None and m["ssim"] is None and m["psnr_frames"] == 0 and "depth" in m["psnr_reason"]
