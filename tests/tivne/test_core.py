"""Stage tests of the SLAM core: grid lookup, field, rendering, losses, keyframes, tracking gradients."""

from __future__ import annotations

import math

import pytest
import torch

from tivne.field.networks import TimeVaryingField
from tivne.field.voxels import CORNER_OFFSETS, GridCapacityError, SparseVoxelGrid, unpack_keys
from tivne.geometry import se3_exp
from tivne.keyframes import KeyframeDatabase, KeyframePolicy, View, overlap_ratios
from tivne.losses import LossWeights, balance_factors, sdf_losses, slam_loss
from tivne.rendering import RayBundle, bell_weights, composite, render_rays, rays_from_pixels
from tivne.sampling import PixelPool, PixelSampler, depth_guided_depths


def brute_force_lookup(grid: SparseVoxelGrid, points: torch.Tensor) -> torch.Tensor:
    """Reference trilinear interpolation from a Python dict of corner -> row."""
    rows = {tuple(c.tolist()): int(r) for c, r in zip(unpack_keys(grid.corner_keys), grid.corner_rows)}
    out = []
    for p in points.double():
        g = p / grid.voxel_size
        base = torch.floor(g)
        frac = g - base
        acc = torch.zeros(grid.embed_dim, dtype=torch.float64)
        for off in CORNER_OFFSETS:
            corner = tuple((base.long() + off).tolist())
            w = torch.prod(torch.where(off.bool(), frac, 1 - frac))
            acc += w * grid.embeddings[rows[corner]].double()
        out.append(acc)
    return torch.stack(out)


def test_grid_lookup_matches_brute_force_and_shares_corners():
    torch.manual_seed(0)
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=4, capacity=8)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [-0.31, 0.42, 1.07]]))
    assert grid.num_voxels == 3
    assert grid.num_corners == 8 + 4 + 8  # two neighbours share a face: 4 corners
    points = torch.tensor([[0.01, 0.02, 0.03], [0.19, 0.08, 0.01], [-0.35, 0.45, 1.02]])
    feats, valid = grid.lookup(points)
    assert valid.all()
    torch.testing.assert_close(feats.double(), brute_force_lookup(grid, points), atol=1e-6, rtol=0)
    _, valid = grid.lookup(torch.tensor([[5.0, 5.0, 5.0], [float("nan"), 0.0, 0.0], [1e9, 0.0, 0.0]]))
    assert not valid.any()


def test_grid_grows_keeps_rows_and_enforces_cap():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=8, max_capacity=40)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]))
    before = grid.embeddings.detach().clone()
    grid.allocate(torch.tensor([[0.35, 0.05, 0.05]]))
    assert grid.capacity >= 16
    torch.testing.assert_close(grid.embeddings.detach()[:8], before[:8])
    with pytest.raises(GridCapacityError, match="max_capacity"):
        grid.allocate(torch.rand(200, 3) * 5)


def test_grid_dilation_allocates_neighbourhood():
    grid = SparseVoxelGrid(voxel_size=0.1)
    assert grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]), dilation=1) == 27
    assert grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]), dilation=1) == 0


def small_field(time: bool = True) -> TimeVaryingField:
    torch.manual_seed(0)
    field = TimeVaryingField(time=time, voxel_size=0.1, hidden_dim=16, capacity=64)
    field.grid.allocate(torch.rand(50, 3) * 0.5)
    return field


def test_offset_is_exactly_zero_at_time_zero_and_not_after():
    field = small_field()
    torch.nn.init.normal_(field.deformation.out.weight)  # a trained-looking, non-zero Θd
    points = torch.rand(30, 3) * 0.5
    at0 = field(points, torch.zeros(30))
    assert at0.valid.any()
    assert at0.offset_sq[at0.valid].abs().max() == 0
    later = field(points, torch.full((30,), 0.7))
    assert later.offset_sq[later.valid].min() > 0


def test_gradients_reach_embeddings_both_mlps_and_pose():
    field = small_field()
    torch.nn.init.normal_(field.deformation.out.weight, std=0.1)
    xi = torch.zeros(1, 6, requires_grad=True)
    points = (torch.rand(40, 3) * 0.4 + 0.05) @ se3_exp(xi)[0, :3, :3].T
    out = field(points, torch.full((40,), 0.5))
    (out.sdf.sum() + out.rgb.sum()).backward()
    assert field.grid.embeddings.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in field.deformation.parameters())
    assert field.canonical.trunk[0].weight.grad.abs().sum() > 0
    assert torch.isfinite(xi.grad).all() and xi.grad.abs().sum() > 0


def test_static_field_ignores_time():
    field = small_field(time=False)
    points = torch.rand(20, 3) * 0.5
    a, b = field(points, torch.zeros(20)), field(points, torch.full((20,), 3.0))
    torch.testing.assert_close(a.sdf, b.sdf)


def test_bell_weights_peak_and_composite_normalises():
    s = torch.linspace(-2, 2, 41)[None]
    w = bell_weights(s, 5.0)
    assert w.argmax() == 20 and torch.allclose(w, w.flip(-1))
    z = torch.linspace(1, 2, 41)[None]
    rgb = torch.rand(1, 41, 3)
    out = composite(w, rgb, z)
    expected = (w / w.sum() * z).sum()
    torch.testing.assert_close(out.depth[0], expected)
    one_hot = torch.zeros(1, 41)
    one_hot[0, 7] = 3.0
    out = composite(one_hot, rgb, z)
    torch.testing.assert_close(out.depth[0], z[0, 7])
    torch.testing.assert_close(out.rgb[0], rgb[0, 7])


class PlaneField(torch.nn.Module):
    """Stub field: the plane z = 2 (world), SDF in truncation units."""

    def __init__(self, truncation: float) -> None:
        super().__init__()
        self.tr = truncation

    def forward(self, points, tau):
        from tivne.field.networks import FieldOutputs

        sdf = (2.0 - points[:, 2]) / self.tr
        return FieldOutputs(sdf=sdf, rgb=torch.full_like(points, 0.5), valid=torch.ones_like(sdf, dtype=torch.bool), offset_sq=torch.zeros_like(sdf))


def test_render_rays_recovers_plane_depth_along_z1_rays():
    K = torch.tensor([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    uv = torch.tensor([[0.0, 0.0], [40.0, 30.0], [79.0, 59.0]])
    origins, dirs = rays_from_pixels(uv, K, torch.eye(4))
    assert torch.allclose(dirs[:, 2], torch.ones(3))
    depth = torch.full((3,), 2.02)  # a slightly wrong observation: samples still bracket the plane
    rays = RayBundle(origins, dirs, torch.zeros(3), torch.zeros(3, 3), depth, torch.zeros(3, dtype=torch.bool))
    z = depth_guided_depths(depth, 0.05, 64, 4, stratified=False)
    rendered, _ = render_rays(PlaneField(0.05), rays, z, 0.05)
    torch.testing.assert_close(rendered.depth, torch.full((3,), 2.0), atol=3e-3, rtol=0)


def test_beta_balancing_and_sdf_losses():
    beta_fs, beta_tr = balance_factors(torch.tensor(30.0), torch.tensor(10.0))
    assert math.isclose(float(beta_fs), 0.25) and math.isclose(float(beta_tr), 0.75)
    z = torch.linspace(1.0, 2.1, 23)[None]
    depth = torch.tensor([2.0])
    perfect = torch.where(z < 1.95, torch.ones_like(z), (depth[:, None] - z) / 0.05)
    fs, sdf = sdf_losses(perfect, z, depth, 0.05)
    assert float(fs) == 0 and float(sdf) < 1e-12
    fs, sdf = sdf_losses(perfect + 0.3, z, depth, 0.05)
    assert float(fs) > 0 and float(sdf) > 0


def test_offset_loss_only_on_background_with_mask():
    n, m = 4, 3
    rays = RayBundle(torch.zeros(n, 3), torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, 3), torch.ones(n),
                     torch.tensor([True, False, False, False]), has_mask=True)
    from tivne.field.networks import FieldOutputs
    from tivne.rendering import RenderedRays

    offset = torch.zeros(n, m)
    offset[0] = 100.0  # a large offset on the dynamic ray must not be penalised
    outputs = FieldOutputs(torch.ones(n, m), torch.zeros(n, m, 3), torch.ones(n, m, dtype=torch.bool), offset)
    rendered = RenderedRays(torch.zeros(n, 3), torch.ones(n), torch.zeros(n), torch.ones(n))
    _, terms = slam_loss(rays, torch.ones(n, m), rendered, outputs, 0.05, LossWeights())
    assert float(terms["offset"]) == 0
    rays.has_mask = False
    _, terms = slam_loss(rays, torch.ones(n, m), rendered, outputs, 0.05, LossWeights())
    assert "offset" not in terms


def test_mask_weighted_sampler_share():
    valid = torch.ones(10, 10, dtype=torch.bool)
    dynamic = torch.zeros(10, 10, dtype=torch.bool)
    dynamic[:2] = True
    pool = PixelPool.from_masks(valid, dynamic)
    idx = PixelSampler("mask_weighted", 0.5)(pool, 1000, torch.Generator().manual_seed(0))
    assert (idx < 20).sum() == 500
    idx = PixelSampler("uniform", 0.0)(pool, 1000, torch.Generator().manual_seed(0))
    assert 100 < (idx < 20).sum() < 300


def test_overlap_ratio_on_known_geometry_and_policy():
    K = torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    uv = torch.stack(torch.meshgrid(torch.arange(64.0), torch.arange(48.0), indexing="xy"), -1).reshape(-1, 2)
    depth = torch.full((uv.shape[0],), 2.0)
    shifted = torch.eye(4)
    shifted[0, 3] = 1.28  # half the 2.56 m wide view of a plane at 2 m
    turned = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # looking backwards
    ratios = overlap_ratios(uv, depth, K, torch.eye(4), torch.stack([torch.eye(4), shifted, turned]), 64, 48)
    assert float(ratios[0]) == 1.0 and float(ratios[2]) == 0.0
    assert abs(float(ratios[1]) - 0.5) < 0.03
    db = KeyframeDatabase(every=1)
    img = torch.zeros(48, 64, 3)
    for i, pose in enumerate([torch.eye(4), shifted, turned, torch.eye(4)]):
        db.add(View(i, 0.0, img, torch.full((48, 64), 2.0), None, pose))
    current = View(9, 0.0, img, torch.full((48, 64), 2.0), None, torch.eye(4))
    picked = KeyframePolicy("overlap", window=2, overlap_pixels=500).select(db, current, K, torch.Generator().manual_seed(0))
    assert len(picked) == 2 and 1 in picked  # the lowest overlap that is still > 0
    assert 2 not in picked  # no overlap at all: excluded
