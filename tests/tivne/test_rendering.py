"""Rays, bell weights, compositing and rendering an analytic field (tivne/rendering.py)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from tivne.field.networks import FieldOutputs
from tivne.geometry import pixel_to_ray, se3_exp
from tivne.rendering import (
    RayBundle,
    RenderConfig,
    bell_weights,
    composite,
    first_surface_mask,
    gather_rays,
    rays_from_pixels,
    render_rays,
)
from tivne.sampling import depth_guided_depths

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


# ---- rays -----------------------------------------------------------------------------------------


def test_rays_have_camera_frame_z_one_so_parameter_is_z_depth():
    pose = random_pose(0)
    gen = torch.Generator().manual_seed(1)
    uv = torch.rand(50, 2, generator=gen) * torch.tensor([80.0, 60.0])
    origins, directions = rays_from_pixels(uv, K, pose)
    assert origins.shape == directions.shape == (50, 3)
    torch.testing.assert_close(origins, pose[:3, 3].expand(50, 3))
    d = torch.rand(50, generator=gen) * 3 + 0.1
    world = origins + directions * d[:, None]
    cam = (world - pose[:3, 3]) @ pose[:3, :3]  # R^T (x - t)
    torch.testing.assert_close(cam[:, 2], d, atol=1e-5, rtol=1e-5)
    # and the point projects back to its pixel
    proj = cam @ K.T
    torch.testing.assert_close(proj[:, :2] / proj[:, 2:], uv, atol=1e-3, rtol=0)


def test_rays_from_pixels_with_per_ray_poses():
    poses = torch.stack([random_pose(0), random_pose(1), random_pose(2)])
    uv = torch.tensor([[3.0, 4.0], [10.0, 50.0], [79.0, 0.0]])
    origins, directions = rays_from_pixels(uv, K, poses)
    for i in range(3):
        o, d = rays_from_pixels(uv[i : i + 1], K, poses[i])
        torch.testing.assert_close(origins[i], o[0])
        torch.testing.assert_close(directions[i], d[0])


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


# ---- gather_rays ----------------------------------------------------------------------------------


def test_gather_rays_concatenates_views_in_order_with_their_poses():
    gen = torch.Generator().manual_seed(0)
    h, w = 6, 8
    imgs = []
    for v in range(2):
        rgb = torch.rand(h, w, 3, generator=gen)
        depth = torch.rand(h, w, generator=gen) + 0.5
        dyn = (torch.rand(h, w, generator=gen) > 0.5) if v == 1 else None
        imgs.append((rgb, depth, dyn, 0.1 * (v + 1)))
    poses = torch.stack([random_pose(1), random_pose(2)])
    pixels = [torch.tensor([0, 9, 47]), torch.tensor([5, 46])]
    rays = gather_rays(pixels, imgs, poses, K)
    assert isinstance(rays, RayBundle) and len(rays) == 5 and rays.has_mask
    for i, (v, idx) in enumerate([(0, 0), (0, 9), (0, 47), (1, 5), (1, 46)]):
        rgb, depth, dyn, tau = imgs[v]
        u, row = idx % w, idx // w
        torch.testing.assert_close(rays.rgb[i], rgb[row, u])
        assert float(rays.depth[i]) == float(depth[row, u])
        assert float(rays.tau[i]) == pytest.approx(tau)
        assert bool(rays.dynamic[i]) == (False if dyn is None else bool(dyn[row, u]))
        torch.testing.assert_close(rays.origins[i], poses[v, :3, 3])
        d_cam = pixel_to_ray(torch.tensor([[float(u), float(row)]]), K)[0]
        torch.testing.assert_close(rays.directions[i], poses[v, :3, :3] @ d_cam)
    no_mask = gather_rays([pixels[0]], [imgs[0]], poses[:1], K)
    assert not no_mask.has_mask and not no_mask.dynamic.any()


def test_gather_rays_is_differentiable_wrt_poses():
    xi = torch.zeros(1, 6, requires_grad=True)
    pose = se3_exp(xi)
    depth = torch.ones(6, 8)
    rays = gather_rays([torch.tensor([3, 20])], [(torch.zeros(6, 8, 3), depth, None, 0.0)], pose, K)
    (rays.origins.sum() + rays.directions.sum()).backward()
    assert xi.grad is not None and xi.grad.abs().sum() > 0


# ---- render_rays on an analytic field --------------------------------------------------------------


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
    rendered, outputs = render_rays(field, rays, z, tr)
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
    rendered, _ = render_rays(field, rays, z, tr)
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
    rendered, outputs = render_rays(field, rays, z, tr)
    assert outputs.valid[0, 2:].all() and not outputs.valid[0, :2].any()
    # every valid sample is negative (no + to - crossing among mapped samples): the ray must keep them
    assert float(rendered.weight_sum[0]) > 0.1
