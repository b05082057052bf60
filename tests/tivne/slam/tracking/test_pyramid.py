"""The odometry's pyramid (tivne.slam.tracking.pyramid): the depth filter, the pick of the tracked pixels."""

from __future__ import annotations

import pytest
import torch

from data_modules.sensor import kinect_depth_sigma
from tivne.slam.tracking.pyramid import build_pyramid, filter_depth, image_gradients, pick_pixels


def _plane(z: float, h: int = 40, w: int = 50) -> torch.Tensor:
    return torch.full((h, w), z, dtype=torch.float64)


def test_noise_on_one_surface_is_smoothed():
    """A fronto-parallel wall at 2.5 m with the sensor's own noise comes out with less than half of it."""
    g = torch.Generator().manual_seed(0)
    truth = _plane(2.5)
    noisy = truth + kinect_depth_sigma(truth) * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    inner = (slice(3, -3), slice(3, -3))  # away from the border, where windows are cut
    before = (noisy - truth)[inner].pow(2).mean().sqrt()
    after = (filter_depth(noisy) - truth)[inner].pow(2).mean().sqrt()
    assert after < 0.5 * before


def test_a_step_to_another_surface_is_kept_exactly():
    """A wall at 1 m beside one at 1.5 m: no pixel takes a depth between the two (the range weight of
    the other surface is exp(-1700) at 3 sigma), so the filtered step equals the input (to float32)."""
    depth = _plane(1.0)
    depth[:, 25:] = 1.5
    assert torch.allclose(filter_depth(depth), depth, rtol=0, atol=1e-6)


def test_invalid_pixels_stay_invalid_and_do_not_pull_their_neighbours():
    depth = _plane(2.0)
    depth[10:14, 20:30] = 0.0
    out = filter_depth(depth)
    assert (out[10:14, 20:30] == 0).all()
    valid = depth > 0
    assert torch.allclose(out[valid], depth[valid], rtol=0, atol=1e-6)


def test_the_pyramid_filters_only_when_asked_and_after_removing_dynamic_pixels():
    """smooth=False leaves the depth as it was; smooth=True filters the depth without the dynamic
    pixels, so a moving object 2 cm in front of a wall (within the range scale) is not averaged in."""
    g = torch.Generator().manual_seed(1)
    depth = _plane(2.0) + 0.004 * torch.randn(40, 50, generator=g, dtype=torch.float64)
    depth[15:25, 15:25] = 1.98
    dynamic = torch.zeros(40, 50, dtype=torch.bool)
    dynamic[15:25, 15:25] = True
    rgb = torch.rand(40, 50, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[50.0, 0, 25], [0, 50.0, 20], [0, 0, 1]], dtype=torch.float64)
    plain = build_pyramid(rgb, depth, K, 2, dynamic)
    smoothed = build_pyramid(rgb, depth, K, 2, dynamic, smooth=True)
    static = torch.where(dynamic, torch.zeros_like(depth), depth)
    assert torch.equal(plain[0].depth, static)
    assert torch.allclose(smoothed[0].depth, filter_depth(static), rtol=0, atol=0)
    assert (smoothed[0].depth[dynamic] == 0).all()
    assert not torch.allclose(smoothed[0].depth, plain[0].depth)


def _level(h: int = 23, w: int = 30):
    g = torch.Generator().manual_seed(2)
    rgb = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[30.0, 0, 15], [0, 30.0, 11], [0, 0, 1]], dtype=torch.float64)
    return build_pyramid(rgb, torch.full((h, w), 2.0, dtype=torch.float64), K, 1)[0]


def test_the_grid_pick_takes_each_tiles_corner():
    level = _level()
    usable = torch.ones_like(level.usable)
    usable[0, 0] = False
    picked = pick_pixels(level, usable, 4)
    expected = torch.zeros_like(usable)
    expected[::4, ::4] = True
    expected[0, 0] = False
    assert torch.equal(picked, expected)


@pytest.mark.parametrize("stride", [2, 4, 7])
def test_the_gradient_pick_takes_each_tiles_strongest_usable_pixel(stride):
    """One pixel in each tile that has a usable one (also the cut tiles at the right and bottom
    border), none in a tile without; each is the usable pixel of the largest gradient there."""
    level = _level()
    usable = torch.rand(level.usable.shape, generator=torch.Generator().manual_seed(3)) > 0.3
    usable[:stride, :stride] = False  # one tile without a usable pixel
    picked = pick_pixels(level, usable, stride, "gradient")
    strength = image_gradients(level.intensity).pow(2).sum(0)
    h, w = usable.shape
    for r in range(0, h, stride):
        for c in range(0, w, stride):
            tile, mask = picked[r:r + stride, c:c + stride], usable[r:r + stride, c:c + stride]
            assert int(tile.sum()) == int(mask.any())
            if mask.any():
                assert (tile & mask).any()
                assert strength[r:r + stride, c:c + stride][tile].max() == strength[r:r + stride, c:c + stride][mask].max()
