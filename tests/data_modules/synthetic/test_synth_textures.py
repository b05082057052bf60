"""Procedural textures: table-driven plane noise equals the hashed fbm, seeding, shading and patterns."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_modules.synthetic.textures import PlaneNoise, Texture, fbm, pattern_value, random_texture, shade, value_noise


@pytest.mark.parametrize("axis, offset, scale", [(0, -0.35, 1.0), (1, 1.5, 1.0), (2, 0.0, 1.3), (2, 2.6, 0.8)])
def test_plane_noise_equals_fbm_on_its_plane(axis, offset, scale):
    lo, hi = np.array([-2.0, -1.5, 0.0]), np.array([2.0, 1.5, 2.6])
    gen = torch.Generator().manual_seed(axis)
    p = torch.from_numpy(lo) + torch.rand(20_000, 3, generator=gen, dtype=torch.float64) * torch.from_numpy(hi - lo)
    p[:, axis] = offset
    table = PlaneNoise(axis, offset, lo, hi, salt=17, scale=scale)
    assert float((table(p.T.contiguous()) - fbm(p, 17, scale)).abs().max()) < 1e-5


def test_value_noise_is_continuous_and_in_range():
    gen = torch.Generator().manual_seed(0)
    p = torch.rand(5000, 3, generator=gen, dtype=torch.float64) * 20 - 10
    v = value_noise(p, 3)
    assert v.dtype == torch.float32 and 0 <= float(v.min()) and float(v.max()) < 1
    # Lattice spacing 1, C1-continuous: a 1e-4 step changes the value by far less than 1e-3.
    assert float((value_noise(p + 1e-4, 3) - v).abs().max()) < 1e-3
    assert not torch.equal(value_noise(p, 4), v)  # the salt selects another field


def test_random_texture_is_seeded():
    a = random_texture(np.random.default_rng(5), "wall")
    assert a == random_texture(np.random.default_rng(5), "wall")
    assert a != random_texture(np.random.default_rng(6), "wall")
    obj = random_texture(np.random.default_rng(5), "object")
    assert obj.pattern in ("noise", "checker", "stripes")
    with pytest.raises(ValueError):
        random_texture(np.random.default_rng(5), "carpet")


def test_shade_is_a_colour_and_bakes_the_light():
    tex = Texture(1, (0.5, 0.5, 0.5), (0.3, 0.3, 0.3), (1.0, 1.0, 1.0), (0.0, 0.3, 0.6))
    noise = torch.linspace(0, 1, 100)
    p = torch.zeros(3, 100, dtype=torch.float64)
    up, down = torch.tensor([[0.0], [0.0], [1.0]], dtype=torch.float64), torch.tensor([[0.0], [0.0], [-1.0]], dtype=torch.float64)
    lit, dark = shade(tex, noise, p, up), shade(tex, noise, p, down)
    assert lit.shape == (100, 3) and lit.dtype == torch.float32
    assert 0 <= float(dark.min()) and float(lit.max()) <= 1
    assert bool((lit.sum(-1) > dark.sum(-1)).all())  # the light comes from above (local frame)


def test_checker_and_stripes_patterns():
    p = torch.tensor([[0.05, 0.05, 0.05], [0.3, 0.05, 0.05], [0.3, 0.3, 0.05], [0.05, 0.05, 0.3]], dtype=torch.float64).T
    checker = Texture(1, (0.5,) * 3, (0.3,) * 3, (1.0,) * 3, (0.0,) * 3, pattern="checker", pattern_size=0.25, pattern_mix=0.3)
    stripes = Texture(1, (0.5,) * 3, (0.3,) * 3, (1.0,) * 3, (0.0,) * 3, pattern="stripes", pattern_size=0.25, pattern_mix=0.3)
    assert pattern_value(p, checker).tolist() == [0.0, 1.0, 0.0, 1.0]
    assert pattern_value(p, stripes).tolist() == [0.0, 0.0, 0.0, 1.0]
