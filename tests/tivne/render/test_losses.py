"""β balancing, SDF / free-space losses, robust ray rejection and the total loss (tivne/losses.py)."""

from __future__ import annotations

import pytest
import torch

from tivne.config import LossWeights
from tivne.field.networks import FieldOutputs
from tivne.render.losses import balance_factors, robust_ray_mask, routed_sdf, sdf_losses, slam_loss
from tivne.render.rays import RayBundle
from tivne.render.renderer import RenderBatch, RenderedRays

TR = 0.1


def perfect_sdf(z: torch.Tensor, depth: torch.Tensor, truncation: float) -> torch.Tensor:
    """Target values: 1 in free space, (D - z)/tr in the band (anything behind the band)."""
    d = depth[:, None]
    return torch.where(z < d - truncation, torch.ones_like(z), (d - z) / truncation)


def sample_grid() -> tuple[torch.Tensor, torch.Tensor]:
    # D = 1: free z < 0.9, truncation band |z - 1| <= 0.1, behind z > 1.1
    z = torch.tensor([[0.2, 0.5, 0.85, 0.95, 1.0, 1.05, 1.3, 1.5]] * 2)
    depth = torch.tensor([1.0, 1.0])
    return z, depth


def test_balance_factors_known_counts():
    b_fs, b_tr = balance_factors(torch.tensor(30.0), torch.tensor(10.0))
    assert float(b_fs) == pytest.approx(0.25) and float(b_tr) == pytest.approx(0.75)
    b_fs, b_tr = balance_factors(torch.tensor(5.0), torch.tensor(15.0))
    assert float(b_fs) == pytest.approx(0.75) and float(b_tr) == pytest.approx(0.25)
    b_fs, b_tr = balance_factors(torch.tensor(8.0), torch.tensor(8.0))
    assert float(b_fs) == float(b_tr) == pytest.approx(0.5)
    # no samples at all: no division by zero
    b_fs, b_tr = balance_factors(torch.tensor(0.0), torch.tensor(0.0))
    assert torch.isfinite(b_fs) and torch.isfinite(b_tr)


def test_sdf_losses_zero_for_perfect_sdf_and_positive_otherwise():
    z, depth = sample_grid()
    sdf = perfect_sdf(z, depth, TR)
    fs, tr = sdf_losses(sdf, z, depth, TR)
    assert float(fs) == pytest.approx(0.0, abs=1e-12) and float(tr) == pytest.approx(0.0, abs=1e-10)
    fs, tr = sdf_losses(sdf + 0.3, z, depth, TR)
    assert fs > 0 and tr > 0


def test_sample_classification_free_band_behind():
    z, depth = sample_grid()
    base = perfect_sdf(z, depth, TR)
    free_cols, band_cols, behind_cols = [0, 1, 2], [3, 4, 5], [6, 7]
    # counts: 3 free and 3 band per ray -> β = 0.5 each; 16 slots
    err = torch.zeros_like(z)
    err[:, free_cols] = 0.5
    fs, tr = sdf_losses(base + err, z, depth, TR)
    assert float(fs) == pytest.approx(0.5 * (6 * 0.25) / 16) and float(tr) == pytest.approx(0.0, abs=1e-10)
    err = torch.zeros_like(z)
    err[:, band_cols] = 0.5
    fs, tr = sdf_losses(base + err, z, depth, TR)
    # band residual: z + s·tr - D = 0.5 · tr
    assert float(fs) == pytest.approx(0.0, abs=1e-12) and float(tr) == pytest.approx(0.5 * (6 * (0.5 * TR) ** 2) / 16, rel=1e-4)
    err = torch.zeros_like(z)
    err[:, behind_cols] = 7.0  # samples behind the band are unconstrained
    fs, tr = sdf_losses(base + err, z, depth, TR)
    assert float(fs) == pytest.approx(0.0, abs=1e-12) and float(tr) == pytest.approx(0.0, abs=1e-10)


def test_sdf_losses_beta_downweights_majority_class():
    z = torch.tensor([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.95]])  # 6 free, 1 band sample
    depth = torch.tensor([1.0])
    sdf = perfect_sdf(z, depth, TR) + 1.0
    fs, tr = sdf_losses(sdf, z, depth, TR)
    assert float(fs) == pytest.approx((1 / 7) * 6 / 7)
    assert float(tr) == pytest.approx((6 / 7) * TR**2 / 7, rel=1e-4)


def test_sdf_losses_ray_mask_excludes_rays():
    z, depth = sample_grid()
    sdf = perfect_sdf(z, depth, TR)
    sdf[1] += 3.0  # ray 1 is wrong
    fs, tr = sdf_losses(sdf, z, depth, TR, ray_mask=torch.tensor([True, False]))
    assert float(fs) == pytest.approx(0.0, abs=1e-12) and float(tr) == pytest.approx(0.0, abs=1e-10)
    fs, tr = sdf_losses(sdf, z, depth, TR, ray_mask=torch.tensor([True, True]))
    assert fs > 0 and tr > 0


def test_routed_sdf_names_the_field_of_the_ray_label():
    nan = float("nan")
    parts = torch.tensor([[[0.1, 0.5]], [[0.2, 0.4]], [[0.3, nan]]])  # static / object SDF
    own, other = routed_sdf(parts, torch.tensor([True, False, True]))
    # object ray: the object's SDF, even where the static part is the smaller; static ray: the static part
    assert own[:, 0].tolist() == pytest.approx([0.5, 0.2, 0.3])
    assert other[0, 0] == pytest.approx(0.1) and other[1, 0] == pytest.approx(0.4)
    assert torch.isnan(other[2, 0])  # an object ray no object field covers regresses the composition alone
    # Where no object field is valid (NaN) nothing leaks into the loss or the gradients.
    z, depth = sample_grid()
    static = torch.zeros_like(z, requires_grad=True)
    objects = torch.full_like(z, nan)
    _, tr = sdf_losses(static * 1.0, z, depth, TR, parts=torch.stack([static, objects], -1), dynamic=torch.tensor([False, True]))
    tr.backward()
    assert torch.isfinite(tr) and torch.isfinite(static.grad).all() and static.grad.abs().sum() > 0


def test_routed_sdf_loss_teaches_the_object_its_surface_and_keeps_the_static_part_above_the_target():
    z, depth = sample_grid()
    target = perfect_sdf(z, depth, TR)
    band = (z - depth[:, None]).abs() <= TR
    dynamic = torch.tensor([True, True])
    # A static copy of the object (exact) and an object field 0.5 off: only the object part is wrong.
    static = target.clone().requires_grad_(True)
    objects = (target + 0.5).requires_grad_(True)
    parts = torch.stack([static, objects], -1)
    _, tr = sdf_losses(torch.minimum(static, objects), z, depth, TR, parts=parts, dynamic=dynamic)
    tr.backward()
    assert float(tr) > 0 and (objects.grad[band] != 0).all()
    assert float(static.grad.abs().sum()) == 0.0  # the exact copy is not below the target: no push
    # Without routing the min hands the whole target to the (already exact) static copy.
    _, plain = sdf_losses(torch.minimum(target, target + 0.5), z, depth, TR)
    assert float(plain) == pytest.approx(0.0, abs=1e-10)
    # A static part below the target on an object ray is pushed up; above it, left alone.
    static_low = (target - 0.5).requires_grad_(True)
    parts = torch.stack([static_low, target], -1)
    _, tr = sdf_losses(torch.minimum(static_low, target), z, depth, TR, parts=parts, dynamic=dynamic)
    tr.backward()
    assert float(tr) > 0 and (static_low.grad[band] < 0).all()
    parts = torch.stack([target + 0.5, target], -1)
    _, tr = sdf_losses(target, z, depth, TR, parts=parts, dynamic=dynamic)
    assert float(tr) == pytest.approx(0.0, abs=1e-10)
    # Static rays: the roles swap.
    parts = torch.stack([target, target - 0.5], -1)
    _, tr = sdf_losses(target - 0.5, z, depth, TR, parts=parts, dynamic=~dynamic)
    assert float(tr) > 0


def test_routed_sdf_unsure_rays_regress_the_composition_and_push_no_other_part():
    nan = float("nan")
    parts = torch.tensor([[[0.1, 0.5]], [[0.2, 0.4]], [[0.3, nan]], [[0.6, 0.2]]])
    dynamic = torch.tensor([True, False, True, False])
    unsure = torch.tensor([True, True, True, False])
    own, other = routed_sdf(parts, dynamic, unsure)
    assert own[:, 0].tolist() == pytest.approx([0.1, 0.2, 0.3, 0.6])  # the min where unsure, the label's part where sure
    assert torch.isnan(other[:3]).all() and other[3, 0] == pytest.approx(0.2)
    sure_own, sure_other = routed_sdf(parts, dynamic, torch.zeros(4, dtype=torch.bool))
    plain_own, plain_other = routed_sdf(parts, dynamic)
    assert torch.equal(sure_own, plain_own) and torch.equal(sure_other.isnan(), plain_other.isnan())
    # A mislabelled edge ray: the static copy already explains it, so the unsure ray leaves both parts alone.
    z, depth = sample_grid()
    target = perfect_sdf(z, depth, TR)
    static, objects = target.clone().requires_grad_(True), (target + 0.5).requires_grad_(True)
    both = torch.tensor([True, True])
    _, tr = sdf_losses(torch.minimum(static, objects), z, depth, TR, parts=torch.stack([static, objects], -1), dynamic=both,
                       unsure=both)
    tr.backward()
    assert float(tr) == pytest.approx(0.0, abs=1e-10) and float(objects.grad.abs().sum()) == 0.0


def rendered(depth: torch.Tensor, wsum: torch.Tensor | None = None, rgb: torch.Tensor | None = None) -> RenderedRays:
    n = depth.shape[0]
    return RenderedRays(
        rgb=torch.zeros(n, 3) if rgb is None else rgb,
        depth=depth,
        depth_var=torch.zeros(n),
        weight_sum=torch.ones(n) if wsum is None else wsum,
    )


def test_robust_ray_mask_drops_outlier():
    gen = torch.Generator().manual_seed(0)
    obs = torch.rand(20, generator=gen) + 1.0
    residual = 0.01 * (1 + torch.rand(20, generator=gen))
    residual[7] = 1.0  # ~100x the median
    keep = robust_ray_mask(rendered(obs + residual), obs, factor=10.0)
    assert keep.sum() == 19 and not keep[7]
    assert robust_ray_mask(rendered(obs + residual), obs, factor=0.0).all()
    assert robust_ray_mask(rendered(obs + residual), obs, factor=200.0).all()


def test_robust_ray_mask_drops_rays_without_weight():
    obs = torch.ones(4)
    keep = robust_ray_mask(rendered(obs, wsum=torch.tensor([1.0, 0.0, 1.0, 1e-9])), obs, factor=10.0)
    assert keep.tolist() == [True, False, True, False]
    none = robust_ray_mask(rendered(obs, wsum=torch.zeros(4)), obs, factor=10.0)
    assert not none.any()


def bundle(n: int, dynamic: torch.Tensor, has_mask: bool) -> RayBundle:
    return RayBundle(
        origins=torch.zeros(n, 3), directions=torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3), tau=torch.zeros(n),
        rgb=torch.full((n, 3), 0.5), depth=torch.ones(n), dynamic=dynamic, has_mask=has_mask,
    )


def outputs_with_offset(z: torch.Tensor, offset_sq: torch.Tensor, valid: torch.Tensor | None = None) -> FieldOutputs:
    n, m = z.shape
    return FieldOutputs(
        sdf=perfect_sdf(z, torch.ones(n), TR), rgb=torch.full((n, m, 3), 0.5),
        valid=torch.ones(n, m, dtype=torch.bool) if valid is None else valid, offset_sq=offset_sq,
    )


def test_offset_term_only_with_mask_and_only_on_background_samples():
    z = torch.tensor([[0.5, 0.95, 1.0, 1.05]] * 4)
    dynamic = torch.tensor([False, True, False, True])
    offset_sq = torch.tensor([[1.0, 1.0, 1.0, 1.0], [50.0] * 4, [3.0, 3.0, 3.0, 3.0], [70.0] * 4])
    valid = torch.ones(4, 4, dtype=torch.bool)
    valid[2, 3] = False  # invalid samples do not count either
    offset_sq[2, 3] = 0.0
    r = rendered(torch.ones(4), rgb=torch.full((4, 3), 0.5))
    w = LossWeights(offset=0.1)
    total_m, terms_m = slam_loss(RenderBatch(bundle(4, dynamic, True), z, outputs_with_offset(z, offset_sq, valid), r), TR, w)
    # background valid samples: ray 0 (4 x 1.0) and ray 2 (3 x 3.0)
    assert float(terms_m["offset"]) == pytest.approx((4 * 1.0 + 3 * 3.0) / 7)
    total_n, terms_n = slam_loss(RenderBatch(bundle(4, torch.zeros(4, dtype=torch.bool), False), z, outputs_with_offset(z, offset_sq, valid), r), TR, w)
    assert "offset" not in terms_n
    assert float(total_m) == pytest.approx(float(total_n) + 0.1 * (13 / 7), rel=1e-5)
    # offset weight 0 switches it off even with a mask
    _, terms_0 = slam_loss(RenderBatch(bundle(4, dynamic, True), z, outputs_with_offset(z, offset_sq, valid), r), TR, LossWeights(offset=0.0))
    assert "offset" not in terms_0


def test_slam_loss_terms_and_weights():
    z = torch.tensor([[0.5, 0.95, 1.0, 1.05]] * 3)
    rays = bundle(3, torch.zeros(3, dtype=torch.bool), False)
    out = outputs_with_offset(z, torch.zeros(3, 4))
    r = rendered(torch.tensor([1.0, 1.2, 0.9]), rgb=torch.tensor([[0.5] * 3, [0.7] * 3, [0.5] * 3]))
    total, terms = slam_loss(RenderBatch(rays, z, out, r), TR, LossWeights(color=2.0, depth=3.0, free_space=0.0, sdf=0.0))
    assert float(terms["depth"]) == pytest.approx((0.0 + 0.2 + 0.1) / 3)
    assert float(terms["color"]) == pytest.approx(0.2 / 3)
    assert float(total) == pytest.approx(2.0 * 0.2 / 3 + 3.0 * 0.3 / 3, rel=1e-5)
    assert float(terms["total"]) == pytest.approx(float(total))
    assert all(not v.requires_grad for v in terms.values())
    # the ray mask restricts the colour and depth averages
    total_m, terms_m = slam_loss(RenderBatch(rays, z, out, r), TR, LossWeights(), ray_mask=torch.tensor([True, False, False]))
    assert float(terms_m["depth"]) == pytest.approx(0.0, abs=1e-7) and float(terms_m["color"]) == pytest.approx(0.0, abs=1e-7)
    # by default rays that rendered no weight are left out
    r0 = rendered(torch.tensor([1.0, 0.0, 0.9]), wsum=torch.tensor([1.0, 0.0, 1.0]))
    _, terms_w = slam_loss(RenderBatch(rays, z, out, r0), TR, LossWeights())
    assert float(terms_w["depth"]) == pytest.approx(0.1 / 2)


def test_slam_loss_gradients_flow_to_render_and_sdf():
    z = torch.tensor([[0.5, 0.95, 1.0, 1.05]] * 2)
    depth = torch.tensor([1.1, 0.8], requires_grad=True)
    sdf = torch.zeros(2, 4, requires_grad=True)
    out = FieldOutputs(sdf=sdf, rgb=torch.zeros(2, 4, 3), valid=torch.ones(2, 4, dtype=torch.bool), offset_sq=torch.zeros(2, 4))
    r = RenderedRays(rgb=torch.zeros(2, 3), depth=depth, depth_var=torch.zeros(2), weight_sum=torch.ones(2))
    total, _ = slam_loss(RenderBatch(bundle(2, torch.zeros(2, dtype=torch.bool), False), z, out, r), TR, LossWeights())
    total.backward()
    assert depth.grad.abs().sum() > 0 and sdf.grad.abs().sum() > 0
