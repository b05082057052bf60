"""Binary morphology on masks (tivne/morphology.py)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from tivne.morphology import dilate, edge_band, edge_band_at, erode


def block(h: int = 12, w: int = 16) -> torch.Tensor:
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[2:6, 3:8] = True
    mask[8:, 12:] = True  # reaches the image corner
    return mask


def test_dilate_grows_by_the_window_and_keeps_the_image_border():
    mask = block()
    grown = dilate(mask, 1)
    expected = torch.zeros_like(mask)
    expected[1:7, 2:9] = True
    expected[7:, 11:] = True
    assert torch.equal(grown, expected)
    assert torch.equal(dilate(mask, 0), mask)


def test_erode_takes_the_border_band_but_not_from_the_image_edge():
    mask = block()
    inner = erode(mask, 1)
    expected = torch.zeros_like(mask)
    expected[3:5, 4:7] = True
    expected[9:, 13:] = True  # the image edge is not an outside
    assert torch.equal(inner, expected)
    assert torch.equal(erode(mask, 0), mask)
    # the same as a max-pool over the complement, the form the tracker had
    outside = F.max_pool2d((~mask).float()[None, None], 5, stride=1, padding=2)[0, 0] > 0
    assert torch.equal(erode(mask, 2), mask & ~outside)


def test_edge_band_is_what_eroding_the_mask_and_its_complement_take():
    mask = block()
    for r in (1, 2):
        assert torch.equal(edge_band(mask, r), ~(erode(mask, r) | erode(~mask, r)))
    assert not edge_band(mask, 0).any()


def test_edge_band_at_reads_the_band_at_pixels_also_at_the_image_border():
    gen = torch.Generator().manual_seed(0)
    mask = torch.rand(23, 31, generator=gen) > 0.7
    mask[:, :4] = True  # a mask reaching the image border
    pixels = torch.arange(mask.numel())
    for radius in (0, 1, 2, 3):
        assert torch.equal(edge_band_at(mask, pixels, radius), edge_band(mask, radius).reshape(-1))
    assert edge_band_at(mask, pixels[:0], 2).shape == (0,)
