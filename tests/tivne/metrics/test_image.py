"""Tests of tivne.metrics.image: MSE, PSNR, SSIM and offline LPIPS."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tivne.metrics import image as M


class TestImageMetrics:
    def test_identical(self):
        img = torch.rand(16, 20, 3, generator=torch.Generator().manual_seed(0))
        assert M.mse(img, img) == 0.0
        assert M.psnr(img, img) == math.inf
        assert M.ssim(img, img) == pytest.approx(1.0, abs=1e-5)

    def test_known_noise_psnr(self):
        gt = torch.full((1, 3, 8, 8), 0.5)
        pred = gt + 0.1  # mse = 0.01 -> 20 dB
        assert M.mse(pred, gt) == pytest.approx(0.01)
        assert M.psnr(pred, gt) == pytest.approx(20.0, abs=1e-4)
        assert M.psnr(pred * 255, gt * 255, max_val=255.0) == pytest.approx(20.0, abs=1e-4)
        rng = np.random.default_rng(0)
        gt = rng.uniform(0.2, 0.8, size=(32, 32, 3))
        pred = gt + rng.normal(scale=0.05, size=gt.shape)
        m = np.mean((pred - gt) ** 2)
        assert M.psnr(pred, gt) == pytest.approx(10 * math.log10(1 / m), abs=1e-9)
        assert M.ssim(torch.from_numpy(pred).float(), torch.from_numpy(gt).float()) < 0.99

    def test_layouts_agree(self):
        gen = torch.Generator().manual_seed(1)
        a, b = torch.rand(12, 14, 3, generator=gen), torch.rand(12, 14, 3, generator=gen)
        a4, b4 = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
        assert M.mse(a, b) == pytest.approx(M.mse(a4, b4))
        assert M.psnr(a, b) == pytest.approx(M.psnr(a4, b4))
        assert M.ssim(a, b) == pytest.approx(M.ssim(a4, b4))

    def test_batch_psnr_is_mean_of_images(self):
        gt = torch.zeros(2, 3, 4, 4)
        pred = torch.stack([torch.full((3, 4, 4), 0.1), torch.full((3, 4, 4), 0.01)])
        assert M.psnr(pred, gt) == pytest.approx(30.0, abs=1e-4)  # (20 + 40) / 2

    def test_mask(self):
        gt = torch.zeros(6, 8, 3)
        pred = gt.clone()
        pred[:3] = 0.1  # error only in the top half
        top = torch.zeros(6, 8, dtype=torch.bool)
        top[:3] = True
        assert M.mse(pred, gt, mask=top) == pytest.approx(0.01)
        assert M.mse(pred, gt, mask=~top) == 0.0
        assert M.mse(pred, gt) == pytest.approx(0.005)
        assert M.psnr(pred, gt, mask=top) == pytest.approx(20.0, abs=1e-4)
        assert M.psnr(pred, gt, mask=~top) == math.inf
        assert math.isnan(M.mse(pred, gt, mask=torch.zeros(6, 8, dtype=torch.bool)))
        assert M.ssim(pred, pred, mask=top) == pytest.approx(1.0, abs=1e-4)  # kornia's eps on flat images
        with pytest.raises(ValueError, match="mask"):
            M.mse(pred, gt, mask=torch.ones(5, 8, dtype=torch.bool))

    def test_bad_shapes(self):
        with pytest.raises(ValueError):
            M.mse(torch.zeros(4, 4), torch.zeros(4, 4))
        with pytest.raises(ValueError):
            M.psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))

    def test_lpips_reports_unavailability_without_download(self, monkeypatch, tmp_path):
        monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache: weights cannot be there
        ok, reason = M.lpips_available()
        assert ok is False and reason
        value, why = M.lpips(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))
        assert value is None and why == reason
        assert not any(tmp_path.rglob("*.pth"))
