"""Tests of tivne.render.rays: z = 1 rays through pixels, bundles of several views."""

from __future__ import annotations

import pytest
import torch

from tivne.geometry import pixel_to_ray, se3_exp
from tivne.render.rays import RayBundle, View, bundle_rays, rays_from_pixels

K = torch.tensor([[60.0, 0.0, 39.5], [0.0, 60.0, 29.5], [0.0, 0.0, 1.0]])


def random_pose(seed: int, scale: float = 0.5) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return se3_exp(torch.randn(6, generator=gen) * scale)


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


# ---- bundle_rays ----------------------------------------------------------------------------------


def test_bundle_rays_concatenates_views_in_order_with_their_poses():
    gen = torch.Generator().manual_seed(0)
    h, w = 6, 8
    imgs = []
    for v in range(2):
        rgb = torch.rand(h, w, 3, generator=gen)
        depth = torch.rand(h, w, generator=gen) + 0.5
        dyn = (torch.rand(h, w, generator=gen) > 0.5) if v == 1 else None
        imgs.append(View(v, 0.1 * (v + 1), rgb, depth, dyn, torch.eye(4)))
    poses = torch.stack([random_pose(1), random_pose(2)])
    pixels = [torch.tensor([0, 9, 47]), torch.tensor([5, 46])]
    rays = bundle_rays(imgs, pixels, poses, K)
    assert isinstance(rays, RayBundle) and len(rays) == 5 and rays.has_mask
    for i, (v, idx) in enumerate([(0, 0), (0, 9), (0, 47), (1, 5), (1, 46)]):
        rgb, depth, dyn, tau = imgs[v].rgb, imgs[v].depth, imgs[v].dynamic, imgs[v].tau
        u, row = idx % w, idx // w
        torch.testing.assert_close(rays.rgb[i], rgb[row, u])
        assert float(rays.depth[i]) == float(depth[row, u])
        assert float(rays.tau[i]) == pytest.approx(tau)
        assert bool(rays.dynamic[i]) == (False if dyn is None else bool(dyn[row, u]))
        torch.testing.assert_close(rays.origins[i], poses[v, :3, 3])
        d_cam = pixel_to_ray(torch.tensor([[float(u), float(row)]]), K)[0]
        torch.testing.assert_close(rays.directions[i], poses[v, :3, :3] @ d_cam)
    no_mask = bundle_rays([imgs[0]], [pixels[0]], poses[:1], K)
    assert not no_mask.has_mask and not no_mask.dynamic.any()


def test_bundle_rays_is_differentiable_wrt_poses():
    xi = torch.zeros(1, 6, requires_grad=True)
    pose = se3_exp(xi)
    depth = torch.ones(6, 8)
    rays = bundle_rays([View(0, 0.0, torch.zeros(6, 8, 3), depth, None, torch.eye(4))], [torch.tensor([3, 20])], pose, K)
    (rays.origins.sum() + rays.directions.sum()).backward()
    assert xi.grad is not None and xi.grad.abs().sum() > 0
