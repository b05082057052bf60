"""Primitives: exact SDF values, ray hits on the zero level set, incidence, area-uniform samples."""

from __future__ import annotations

import math

import pytest
import torch

from data_modules.synthetic.shapes import (
    CURVED,
    Box,
    Cylinder,
    Sphere,
    bound_half,
    planar_faces,
    shape_area,
    shape_raycast,
    shape_sample,
    shape_sdf,
)

SHAPES = [Box((0.3, 0.2, 0.1)), Sphere(0.25), Cylinder(0.2, 0.3)]


def _grad(shape, p: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """(N, 3) numerical SDF gradient (the outward normal on the surface)."""
    g = torch.stack([shape_sdf(shape, p + eps * e) - shape_sdf(shape, p - eps * e) for e in torch.eye(3, dtype=p.dtype)], -1)
    return g / g.norm(dim=-1, keepdim=True)


def test_sdf_exact_values():
    box = Box((0.3, 0.2, 0.1))
    p = torch.tensor([[0.0, 0.0, 0.0], [1.3, 0.0, 0.0], [1.3, 1.2, 0.0], [0.0, 0.0, 0.05]], dtype=torch.float64)
    assert torch.allclose(shape_sdf(box, p), torch.tensor([-0.1, 1.0, math.sqrt(2.0), -0.05], dtype=torch.float64))
    cyl = Cylinder(0.2, 0.3)
    q = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.7], [0.5, 0.0, 0.7]], dtype=torch.float64)
    assert torch.allclose(shape_sdf(cyl, q), torch.tensor([-0.2, 0.3, 0.4, 0.5], dtype=torch.float64))
    assert float(shape_sdf(Sphere(0.25), q[1:2])) == pytest.approx(0.25)


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: type(s).__name__)
def test_ray_hits_are_exact_first_entries(shape):
    gen = torch.Generator().manual_seed(0)
    o = torch.tensor([0.9, -1.1, 0.6], dtype=torch.float64)
    aim = (torch.rand(4000, 3, generator=gen, dtype=torch.float64) * 2 - 1) * torch.from_numpy(bound_half(shape)) * 1.4
    d = (aim - o) * 0.7  # any length: the ray parameter scales with it
    t, face, incidence = shape_raycast(shape, o, d.T.contiguous())
    hit = torch.isfinite(t)
    assert 0.2 < float(hit.float().mean()) < 0.95
    p = o + t[hit, None] * d[hit]
    assert float(shape_sdf(shape, p).abs().max()) < 1e-12
    for frac in (0.3, 0.9, 0.999):  # nothing in front of the hit
        assert bool((shape_sdf(shape, o + frac * t[hit, None] * d[hit]) > 0).all())
    # Misses stay outside: densely sampled along the ray.
    s = torch.linspace(0, 3, 600, dtype=torch.float64)
    miss_pts = (o + s[:, None, None] * d[~hit][None]).reshape(-1, 3)
    assert bool((shape_sdf(shape, miss_pts) > -1e-9).all())
    n = _grad(shape, p)
    dn = d[hit] / d[hit].norm(dim=-1, keepdim=True)
    assert torch.allclose(incidence[hit] / d[hit].norm(dim=-1), (n * dn).sum(-1).abs(), atol=1e-5)
    if isinstance(shape, Sphere):
        assert bool((face[hit] == CURVED).all())
    else:
        planar = face[hit] != CURVED
        axis = face[hit][planar] // 2
        sign = torch.where(face[hit][planar] % 2 == 1, 1.0, -1.0).to(torch.float64)
        assert torch.allclose(n[planar].gather(1, axis[:, None])[:, 0], sign, atol=1e-6)


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: type(s).__name__)
def test_samples_are_area_uniform_on_the_surface(shape):
    gen = torch.Generator().manual_seed(1)
    p, n = shape_sample(shape, 30_000, gen)
    assert p.shape == n.shape == (30_000, 3)
    assert float(shape_sdf(shape, p).abs().max()) < 1e-12
    assert bool((p.abs() <= torch.from_numpy(bound_half(shape)) + 1e-12).all())
    agree = (n * _grad(shape, p)).sum(-1) > 0.999  # outward normals (gradient ambiguous on edges)
    assert float(agree.float().mean()) > 0.995
    total = shape_area(shape)
    for face, offset, area in planar_faces(shape):
        on_face = (p[:, face // 2] - offset).abs() < 1e-12
        assert float(on_face.float().mean()) == pytest.approx(area / total, abs=0.012)


def test_scaled_shapes_scale_every_extent():
    from data_modules.synthetic.shapes import scaled

    assert scaled(Box((0.1, 0.2, 0.3)), 0.5) == Box((0.05, 0.1, 0.15))
    assert scaled(Sphere(0.2), 1.5) == Sphere(0.2 * 1.5)
    assert scaled(Cylinder(0.1, 0.4), 0.5) == Cylinder(0.05, 0.2)
