"""Pixel pools, pixel samplers and depth-guided sample placement (tivne/sampling.py)."""

from __future__ import annotations

import pytest
import torch

from tivne.config import SamplerConfig
from tivne.morphology import edge_band
from tivne.render.samplers import (
    PixelPool,
    PixelSampler,
    depth_guided_depths,
    draw,
    sample_from_mask,
)


def masks(seed: int = 0, h: int = 12, w: int = 16):
    gen = torch.Generator().manual_seed(seed)
    valid = torch.rand(h, w, generator=gen) > 0.2
    dynamic = torch.zeros(h, w, dtype=torch.bool)
    dynamic[2:6, 3:8] = True
    return valid, dynamic


def test_draw_and_sample_from_mask():
    cand = torch.tensor([4, 9, 11])
    out = draw(cand, 100, torch.Generator().manual_seed(0))
    assert out.shape == (100,) and set(out.tolist()) <= {4, 9, 11} and len(set(out.tolist())) == 3
    assert draw(cand[:0], 10).numel() == 0 and draw(cand, 0).numel() == 0
    mask = torch.zeros(4, 5, dtype=torch.bool)
    mask[1, 2] = mask[3, 4] = True
    idx = sample_from_mask(mask, 50, torch.Generator().manual_seed(0))
    assert set(idx.tolist()) == {1 * 5 + 2, 3 * 5 + 4}
    assert sample_from_mask(torch.zeros(3, 3, dtype=torch.bool), 5).numel() == 0


def test_draw_is_deterministic_given_generator():
    cand = torch.arange(1000)
    a = draw(cand, 64, torch.Generator().manual_seed(3))
    b = draw(cand, 64, torch.Generator().manual_seed(3))
    assert torch.equal(a, b)


def test_pixel_pool_split_by_mask():
    valid, dynamic = masks()
    pool = PixelPool.from_masks(valid, dynamic)
    flat_v, flat_d = valid.reshape(-1), dynamic.reshape(-1)
    assert pool.valid.tolist() == flat_v.nonzero()[:, 0].tolist()
    assert pool.dynamic.tolist() == (flat_v & flat_d).nonzero()[:, 0].tolist()
    assert pool.static.tolist() == (flat_v & ~flat_d).nonzero()[:, 0].tolist()
    assert pool.dynamic.numel() + pool.static.numel() == pool.valid.numel()
    assert pool.dynamic.numel() > 0
    no_mask = PixelPool.from_masks(valid, None)
    assert no_mask.dynamic.numel() == 0 and torch.equal(no_mask.static, no_mask.valid)


def test_edge_band_is_the_ring_on_both_sides_of_the_mask_edge():
    _, dynamic = masks()  # rows 2:6, columns 3:8
    band = edge_band(dynamic, 1)
    ring = torch.zeros_like(dynamic)
    ring[1:7, 2:9] = True
    ring[3:5, 4:7] = False  # the interior a pixel away from the edge
    assert torch.equal(band, ring)
    assert not edge_band(dynamic, 0).any()
    assert not edge_band(torch.zeros_like(dynamic), 1).any() and not edge_band(torch.ones_like(dynamic), 1).any()
    assert edge_band(dynamic, 2).sum() > band.sum() and bool((band & ~edge_band(dynamic, 2)).sum() == 0)


def test_pixel_pool_leaves_out_the_mask_edge_band():
    valid, dynamic = masks()
    pool = PixelPool.from_masks(valid, dynamic, edge=1)
    band = edge_band(dynamic, 1).reshape(-1)
    kept = (valid.reshape(-1) & ~band).nonzero()[:, 0]
    assert torch.equal(pool.valid, kept)
    assert not band[pool.dynamic].any() and not band[pool.static].any()
    assert dynamic.reshape(-1)[pool.dynamic].all() and pool.dynamic.numel() > 0  # the interior stays
    assert torch.equal(PixelPool.from_masks(valid, dynamic, edge=0).valid, PixelPool.from_masks(valid, dynamic).valid)
    assert torch.equal(PixelPool.from_masks(valid, None, edge=1).valid, valid.reshape(-1).nonzero()[:, 0])  # no mask: no band


def test_pixel_pool_marks_the_label_edge_unsure_and_keeps_those_pixels():
    valid, dynamic = masks()
    pool = PixelPool.from_masks(valid, dynamic, label_edge=1)
    assert torch.equal(pool.valid, PixelPool.from_masks(valid, dynamic).valid)  # marked, not left out
    pixels = torch.arange(valid.numel())
    assert torch.equal(pool.is_unsure(pixels), edge_band(dynamic, 1).reshape(-1))
    still = PixelPool.from_masks(valid, torch.zeros_like(dynamic), label_edge=1)
    for other in (PixelPool.from_masks(valid, dynamic), PixelPool.from_masks(valid, None, label_edge=1), still):
        assert not other.is_unsure(pixels).any()  # off, no mask or nothing moving: every label is trusted


@pytest.mark.parametrize("share", [0.25, 0.5])
def test_mask_weighted_sampler_respects_dynamic_share(share):
    valid, dynamic = masks()
    pool = PixelPool.from_masks(valid, dynamic)
    n = 400
    idx = PixelSampler(SamplerConfig("mask_weighted", share))(pool, n, torch.Generator().manual_seed(0))
    assert idx.shape == (n,)
    is_dyn = dynamic.reshape(-1)[idx]
    assert int(is_dyn.sum()) == round(n * share)  # exact counts, not a probability
    assert valid.reshape(-1)[idx].all()  # only pixels with depth


def test_uniform_sampler_follows_pixel_share():
    valid, dynamic = masks()
    pool = PixelPool.from_masks(valid, dynamic)
    idx = PixelSampler(SamplerConfig("uniform", 0.0))(pool, 4000, torch.Generator().manual_seed(0))
    frac = float(dynamic.reshape(-1)[idx].float().mean())
    expected = pool.dynamic.numel() / pool.valid.numel()
    assert abs(frac - expected) < 0.03
    assert valid.reshape(-1)[idx].all()


def test_sampler_falls_back_to_uniform_without_mask_or_dynamic_pixels():
    valid, dynamic = masks()
    sampler = PixelSampler(SamplerConfig("mask_weighted", 0.5))
    no_mask = PixelPool.from_masks(valid, None)
    a = sampler(no_mask, 300, torch.Generator().manual_seed(1))
    b = PixelSampler(SamplerConfig("uniform", 0.0))(no_mask, 300, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)  # identical draw: the uniform path
    empty_dyn = PixelPool.from_masks(valid, torch.zeros_like(dynamic))
    c = sampler(empty_dyn, 300, torch.Generator().manual_seed(1))
    assert c.shape == (300,) and valid.reshape(-1)[c].all()
    assert sampler(PixelPool.from_masks(torch.zeros_like(valid), dynamic), 10).numel() == 0


def test_sampler_rejects_bad_share():
    with pytest.raises(ValueError, match="dynamic_share"):
        SamplerConfig("x", 1.5)
    with pytest.raises(ValueError, match="dynamic_share"):
        SamplerConfig("x", -0.1)


def test_depth_guided_depths_layout():
    depth = torch.tensor([0.3, 1.0, 2.5, 0.12])
    tr, band, near, n_band, n_free = 0.05, 2.0, 0.05, 12, 4
    z = depth_guided_depths(depth, tr, n_band, n_free, band, near, stratified=True, generator=torch.Generator().manual_seed(0))
    assert z.shape == (4, n_free + n_band)
    assert (z.diff(dim=1) >= 0).all()  # ascending
    assert (z >= near).all() and (z <= depth[:, None] + band * tr).all()
    lo = (depth - band * tr).clamp_min(near)
    band_z, free_z = z[:, n_free:], z[:, :n_free]
    assert ((band_z >= lo[:, None]) & (band_z <= depth[:, None] + band * tr)).all()
    assert (free_z <= lo[:, None]).all()
    # one band sample per stratum
    width = (depth + band * tr - lo) / n_band
    stratum = ((band_z - lo[:, None]) / width[:, None]).floor().clamp(max=n_band - 1)
    assert torch.equal(stratum, torch.arange(n_band, dtype=z.dtype).expand(4, -1))
    # the band reaching the near plane collapses the free samples onto it
    assert torch.allclose(z[3, :n_free], torch.full((n_free,), near))


def test_depth_guided_depths_deterministic_midpoints():
    depth = torch.tensor([1.0, 2.0])
    a = depth_guided_depths(depth, 0.1, 4, 2, band=1.0, near=0.1, stratified=False)
    b = depth_guided_depths(depth, 0.1, 4, 2, band=1.0, near=0.1, stratified=False)
    assert torch.equal(a, b)
    # band [0.9, 1.1] in 4 strata -> midpoints; free [0.1, 0.9] in 2 strata -> midpoints
    torch.testing.assert_close(a[0], torch.tensor([0.3, 0.7, 0.925, 0.975, 1.025, 1.075]))
    assert depth_guided_depths(depth, 0.1, 4, 0, stratified=False).shape == (2, 4)


def test_depth_guided_depths_stratified_is_seeded():
    depth = torch.rand(10, generator=torch.Generator().manual_seed(0)) + 0.5
    a = depth_guided_depths(depth, 0.05, 8, 4, generator=torch.Generator().manual_seed(7))
    b = depth_guided_depths(depth, 0.05, 8, 4, generator=torch.Generator().manual_seed(7))
    c = depth_guided_depths(depth, 0.05, 8, 4, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)
