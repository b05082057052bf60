"""Rays, bell weights, compositing and rendering an analytic field (tivne/rendering.py)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from tivne.config import RenderConfig
from tivne.field.networks import FieldOutputs
from tivne.geometry import se3_exp
from tivne.render.rays import RayBundle, View, rays_from_pixels
from tivne.render.renderer import (
    bell_weights,
    composite,
    first_surface_mask,
    render_image,
    render_pixels,
    render_samples,
)
from tivne.render.samplers import depth_guided_depths

K = torch.tensor([[60.0, 0.0, 39.5], [0.0, 60.0, 29.5], [0.0, 0.0, 1.0]])


def random_pose(seed: int, scale: float = 0.5) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return se3_exp(torch.randn(6, generator=gen) * scale)


class PlaneField(nn.Module):
    """Stub with TimeVaryingField's call signature: SDF of the plane n·x = c in truncation units
    (positive on the camera side), constant colour, every point valid."""

    def __init__(self, normal, offset: float, truncation: float, color=(0.2, 0.5, 0.8)) -> None:
        super().__init__()
        n = torch.as_tensor(normal, dtype=torch.float32)
        self.normal = n / n.norm()
        self.offset = offset
        self.truncation = truncation
        self.color = torch.tensor(color)
        self.calls = 0

    def forward(self, points: torch.Tensor, tau: torch.Tensor) -> FieldOutputs:
        assert points.ndim == 2 and points.shape[1] == 3 and tau.shape == points.shape[:1]
        self.calls += 1
        sdf = (self.offset - points @ self.normal) / self.truncation
        n = points.shape[0]
        return FieldOutputs(
            sdf=sdf, rgb=self.color.expand(n, 3).clone(), valid=torch.ones(n, dtype=torch.bool), offset_sq=torch.zeros(n)
        )


# ---- weights and compositing ----------------------------------------------------------------------


def test_bell_weights_peak_at_zero_and_are_symmetric():
    s = torch.linspace(-3, 3, 61)[None]
    w = bell_weights(s, 1.0 / 0.05)
    assert int(w.argmax()) == 30 and float(w[0, 30]) == pytest.approx(0.25)
    torch.testing.assert_close(w, w.flip(-1))
    assert (w[0, 31:].diff() < 0).all()  # decreasing away from the surface
    # sharpness scales the argument: k·s
    torch.testing.assert_close(bell_weights(s, 2.0), bell_weights(2 * s, 1.0))
    assert (bell_weights(s, 1.0) > 0).all()


def test_composite_one_hot_weight_gives_exact_depth_and_colour():
    z = torch.tensor([[1.0, 1.5, 2.0, 2.5], [0.5, 0.7, 0.9, 1.1]])
    rgb = torch.rand(2, 4, 3, generator=torch.Generator().manual_seed(0))
    w = torch.zeros(2, 4)
    w[0, 2] = 0.3
    w[1, 0] = 5.0
    out = composite(w, rgb, z)
    torch.testing.assert_close(out.depth, torch.tensor([2.0, 0.5]), atol=1e-6, rtol=0)
    torch.testing.assert_close(out.rgb, torch.stack([rgb[0, 2], rgb[1, 0]]), atol=1e-6, rtol=0)
    torch.testing.assert_close(out.depth_var, torch.zeros(2), atol=1e-6, rtol=0)
    torch.testing.assert_close(out.weight_sum, torch.tensor([0.3, 5.0]))


def test_composite_normalises_weights_per_ray():
    gen = torch.Generator().manual_seed(0)
    z = torch.sort(torch.rand(5, 6, generator=gen) * 3, dim=1).values
    rgb = torch.rand(5, 6, 3, generator=gen)
    w = torch.rand(5, 6, generator=gen)
    w[3] = 0  # a ray with no weight renders zeros rather than NaN
    a = composite(w, rgb, z)
    b = composite(w * 17.0, rgb, z)  # scaling a ray's weights changes nothing but weight_sum
    torch.testing.assert_close(a.depth, b.depth)
    torch.testing.assert_close(a.rgb, b.rgb)
    wn = w / w.sum(1, keepdim=True).clamp_min(1e-12)
    expected = (wn * z).sum(1)
    expected[3] = 0
    torch.testing.assert_close(a.depth, expected, atol=1e-5, rtol=0)
    # a normalised depth lies within the ray's sample span (convex combination)
    live = torch.arange(5) != 3
    assert (a.depth[live] >= z[live].min(1).values - 1e-6).all() and (a.depth[live] <= z[live].max(1).values + 1e-6).all()
    assert torch.isfinite(a.rgb).all() and (a.depth[3] == 0) and (a.weight_sum[3] == 0)
    var = (wn * (z - expected[:, None]) ** 2).sum(1)
    var[3] = 0
    torch.testing.assert_close(a.depth_var, var, atol=1e-5, rtol=0)


def test_first_surface_mask_keeps_up_to_one_truncation_behind_first_crossing():
    tr = 0.1
    z = torch.tensor([[1.0, 1.05, 1.1, 1.15, 1.2, 1.25, 1.3, 1.35, 1.4]])
    # + + - - - + + - -  : first + to - crossing between 1.05 and 1.1 (z_first = 1.05)
    sdf = torch.tensor([[1.0, 0.5, -0.2, -0.5, -0.1, 0.3, 0.6, -0.4, -0.8]])
    keep = first_surface_mask(sdf, z, tr)
    assert keep[0].tolist() == [z_ <= 1.05 + tr + 1e-6 for z_ in z[0].tolist()]
    assert keep[0].tolist() == [True, True, True, True, False, False, False, False, False]
    # no crossing (all positive, or only - to +): everything kept
    none = first_surface_mask(torch.tensor([[1.0, 0.5, 0.2, 0.1], [-1.0, -0.5, 0.5, 1.0]]), z[:, :4].expand(2, 4), tr)
    assert none.all()


def test_first_surface_mask_per_ray():
    z = torch.linspace(0, 1, 11)[None].expand(2, 11)
    sdf = torch.stack([0.5 - z[0], 0.2 - z[1]])  # crossings at 0.5 and 0.2
    keep = first_surface_mask(sdf, z, 0.15)
    # z_first: last positive sample (0.4 and 0.1), kept up to z_first + 0.15
    assert keep[0].sum() == 6 and keep[1].sum() == 3


# ---- render_samples on an analytic field --------------------------------------------------------------


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, -0.2, 1.0)])
def test_render_rays_recovers_plane_depth(normal):
    tr = 0.05
    cfg = RenderConfig(truncation=tr, n_band=32, n_free=4)
    pose = se3_exp(torch.tensor([0.05, -0.02, 0.1, 0.02, -0.03, 0.01]))
    field = PlaneField(normal=normal, offset=0.0, truncation=tr)
    # put the plane 1.6 m in front of the camera along its optical axis
    field.offset = float((pose[:3, 3] + 1.6 * pose[:3, 2]) @ field.normal)
    gen = torch.Generator().manual_seed(0)
    uv = torch.rand(64, 2, generator=gen) * torch.tensor([79.0, 59.0])
    origins, directions = rays_from_pixels(uv, K, pose)
    true_depth = (field.offset - origins @ field.normal) / (directions @ field.normal)  # ray parameter at the plane
    assert ((true_depth - 1.6).abs() < 1.0).all() and ((true_depth - 1.6).abs() > 1e-3).any()
    observed = true_depth + (torch.rand(64, generator=gen) - 0.5) * 0.04  # samples centred off the surface
    rays = RayBundle(origins, directions, torch.zeros(64), torch.zeros(64, 3), observed, torch.zeros(64, dtype=torch.bool))
    z = depth_guided_depths(observed, tr, cfg.n_band, cfg.n_free, cfg.band, cfg.near, stratified=False)
    rendered, outputs = render_samples(field, rays, z, tr)
    assert field.calls == 1  # one batched forward pass
    assert outputs.sdf.shape == z.shape and outputs.rgb.shape == (*z.shape, 3) and outputs.valid.shape == z.shape
    assert (rendered.depth - true_depth).abs().max() < 0.005  # a few mm
    torch.testing.assert_close(rendered.rgb, field.color.expand(64, 3), atol=1e-5, rtol=0)
    assert (rendered.weight_sum > 0).all()


def test_render_rays_ignores_invalid_samples():
    """Samples outside the map (valid False) get zero weight: a ray fully outside renders nothing."""

    class Outside(PlaneField):
        def forward(self, points, tau):
            out = super().forward(points, tau)
            out.valid = points[:, 0] < 0  # only rays on the x < 0 side are mapped
            return out

    tr = 0.05
    field = Outside(normal=(0.0, 0.0, 1.0), offset=1.0, truncation=tr)
    origins = torch.tensor([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    depth = torch.tensor([1.0, 1.0])
    rays = RayBundle(origins, directions, torch.zeros(2), torch.zeros(2, 3), depth, torch.zeros(2, dtype=torch.bool))
    z = depth_guided_depths(depth, tr, 16, 2, stratified=False)
    rendered, _ = render_samples(field, rays, z, tr)
    assert rendered.weight_sum[0] > 0 and rendered.weight_sum[1] == 0
    assert abs(float(rendered.depth[0]) - 1.0) < 0.005 and float(rendered.depth[1]) == 0.0


def test_invalid_fill_is_not_a_surface_crossing():
    class GapThenNegative(PlaneField):
        """Unmapped in front of z = 0.8; mapped behind it with a field that is negative there."""

        def forward(self, points, tau):
            out = super().forward(points, tau)
            out.valid = points[:, 2] > 0.8
            out.sdf = torch.where(out.valid, torch.full_like(out.sdf, -0.07), torch.ones_like(out.sdf))
            return out

    tr = 0.05
    field = GapThenNegative(normal=(0.0, 0.0, 1.0), offset=2.0, truncation=tr)
    depth = torch.tensor([2.0])
    rays = RayBundle(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), torch.zeros(1), torch.zeros(1, 3), depth, torch.zeros(1, dtype=torch.bool))
    z = depth_guided_depths(depth, tr, 12, 4, stratified=False)  # free samples at 0.24, 0.71 (unmapped), 1.19, 1.66
    rendered, outputs = render_samples(field, rays, z, tr)
    assert outputs.valid[0, 2:].all() and not outputs.valid[0, :2].any()
    # every valid sample is negative (no + to - crossing among mapped samples): the ray must keep them
    assert float(rendered.weight_sum[0]) > 0.1


# ---- render_pixels / render_image: the one render path ---------------------------------------------


def plane_view(depth_value: float = 1.5) -> View:
    """A fronto-parallel plane at z = depth_value seen by the identity camera (80x60), a hole at (0, 0)."""
    depth = torch.full((60, 80), depth_value)
    depth[0, 0] = 0.0
    return View(3, 0.25, torch.full((60, 80, 3), 0.5), depth, None, torch.eye(4))


def test_render_pixels_bundles_samples_outputs_and_composite_of_the_chosen_pixels():
    tr = 0.05
    field = PlaneField((0.0, 0.0, -1.0), -1.5, tr)  # n·x = c with n = -z: the plane z = 1.5
    cfg = RenderConfig(truncation=tr, n_band=16, n_free=4)
    pixels = torch.tensor([81, 100, 4000])
    batch = render_pixels(field, [plane_view()], [pixels], torch.eye(4)[None], K, cfg, stratified=False)
    assert len(batch.rays) == 3 and batch.z.shape == (3, 20)
    assert batch.outputs.sdf.shape == (3, 20) and batch.outputs.rgb.shape == (3, 20, 3)
    torch.testing.assert_close(batch.rendered.depth, torch.full((3,), 1.5), atol=2e-3, rtol=0)
    assert torch.allclose(batch.rays.tau, torch.full((3,), 0.25))


def test_render_image_renders_every_strided_pixel_with_depth_and_leaves_holes_black():
    tr = 0.05
    field = PlaneField((0.0, 0.0, -1.0), -1.5, tr)
    cfg = RenderConfig(truncation=tr, n_band=16, n_free=4, chunk=500)  # several chunks
    rgb, depth = render_image(field, plane_view(), K, cfg, stride=2)
    assert rgb.shape == (30, 40, 3) and depth.shape == (30, 40)
    assert float(depth[0, 0]) == 0.0 and float(rgb[0, 0].sum()) == 0.0  # the hole
    torch.testing.assert_close(depth[1:, 1:], torch.full((29, 39), 1.5), atol=2e-3, rtol=0)
    torch.testing.assert_close(rgb[5, 5], field.color, atol=1e-5, rtol=0)
