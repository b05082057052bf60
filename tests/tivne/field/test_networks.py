"""Time encoding, Θd, Θs and the assembled time-varying field (tivne/field/networks.py)."""

from __future__ import annotations

import math

import pytest
import torch

from tivne.field.networks import (
    CanonicalMLP,
    DeformationMLP,
    FieldOutputs,
    TimeVaryingField,
    time_encoding,
)


def randomise_output_layer(deformation: DeformationMLP, seed: int = 0, scale: float = 0.5) -> None:
    """Give Θd's (zero-initialised) output layer non-zero weights, as after training."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        deformation.out.weight.copy_(torch.randn(deformation.out.weight.shape, generator=gen) * scale)
        deformation.out.bias.copy_(torch.randn(deformation.out.bias.shape, generator=gen) * scale)


def small_field(time: bool = True, seed: int = 0, **kw) -> TimeVaryingField:
    torch.manual_seed(seed)
    field = TimeVaryingField(time=time, voxel_size=0.1, embed_dim=8, capacity=64, hidden_dim=16, init_std=0.5, **kw)
    field.grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]), dilation=1)
    return field


def inside_points(n: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=gen) * 0.28 - 0.09)  # inside the 3x3x3 block around the origin voxel


# ---- time encoding --------------------------------------------------------------------------------


def test_time_encoding_shape_and_values():
    tau = torch.tensor([0.0, 0.25, -1.5])
    code = time_encoding(tau, 3)
    assert code.shape == (3, 7)
    torch.testing.assert_close(code[:, 0], tau)
    for k in range(3):
        torch.testing.assert_close(code[:, 1 + k], torch.sin(2**k * math.pi * tau))
        torch.testing.assert_close(code[:, 4 + k], torch.cos(2**k * math.pi * tau))
    # τ = 0: (0, 0..0, 1..1)
    assert code[0].tolist() == [0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
    assert time_encoding(tau, 0).shape == (3, 1)
    assert time_encoding(tau.double(), 2).dtype == torch.float64


def test_time_encoding_lowest_octave_keeps_later_times_apart():
    tau = torch.tensor([0.5, 2.5])  # two time units apart: the k0 = 0 phases repeat
    same = time_encoding(tau, 4)
    assert torch.allclose(same[0, 1:], same[1, 1:], atol=1e-5)  # only the linear τ differs
    low = time_encoding(tau, 8, lowest_octave=-4)  # slowest pair: π/16, one period per 32 units
    assert low.shape == (2, 17) and (low[0, 1:] - low[1, 1:]).abs().max() > 0.3
    assert torch.allclose(low[:, 1 + 4], same[:, 1])  # k = 0 is the same pair in both


# ---- Θd -------------------------------------------------------------------------------------------


def test_deformation_is_zero_initialised():
    torch.manual_seed(0)
    d = DeformationMLP(embed_dim=8, time_dim=9, hidden_dim=16)
    e = torch.randn(10, 8)
    tau = torch.full((10,), 0.7)
    assert (d(e, tau, time_encoding(tau, 4)) == 0).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_deformation_exactly_zero_at_time_zero_for_any_weights(seed):
    torch.manual_seed(seed)
    d = DeformationMLP(embed_dim=8, time_dim=9, hidden_dim=16, ramp=0.1)
    randomise_output_layer(d, seed)
    e = torch.randn(32, 8) * 10
    tau0 = torch.zeros(32)
    delta = d(e, tau0, time_encoding(tau0, 4))
    assert (delta == 0).all()
    # ... and genuinely non-zero away from τ = 0 with the same weights
    for t in (1e-3, 0.05, 1.0, -0.5):
        tau = torch.full((32,), t)
        delta = d(e, tau, time_encoding(tau, 4))
        assert (delta.abs().sum(-1) > 0).all()


def gated_full_pass(d: DeformationMLP, e: torch.Tensor, tau: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
    """Θd written out without the τ = 0 shortcut: tanh(τ / ramp) · MLP(e, γ(τ))."""
    return torch.tanh(tau / d.ramp)[:, None] * d.out(d.trunk(torch.cat([e, code], dim=-1)))


def test_time_zero_shortcut_gives_the_full_pass_outputs_and_gradients():
    field = small_field()
    randomise_output_layer(field.deformation)
    pts, tau0 = inside_points(64), torch.zeros(64)

    def outputs_and_grads(full: bool):
        field.zero_grad(set_to_none=True)
        if full:  # the same field with Θd's forward replaced by the plain formula
            field.deformation.forward = lambda e, tau, code: gated_full_pass(field.deformation, e, tau, code)
        try:
            out = field(pts, tau0)
        finally:
            field.deformation.__dict__.pop("forward", None)
        (out.sdf.sum() + out.rgb.sum() + out.offset_sq.sum()).backward()
        return out, {n: p.grad for n, p in field.named_parameters()}

    short, short_grads = outputs_and_grads(False)
    full, full_grads = outputs_and_grads(True)
    assert torch.equal(short.sdf, full.sdf) and torch.equal(short.rgb, full.rgb)
    for name, grad in full_grads.items():
        # Θd's weights get zero gradients, not none: Adam's step counts then match the full pass
        assert short_grads[name] is not None and torch.equal(short_grads[name], grad), name
    assert all((g == 0).all() for n, g in short_grads.items() if n.startswith("deformation."))
    assert short_grads["grid.embeddings"].abs().sum() > 0


def test_deformation_gate_is_tanh_ramp():
    torch.manual_seed(0)
    d = DeformationMLP(embed_dim=4, time_dim=1, hidden_dim=8, ramp=0.2)
    randomise_output_layer(d)
    e = torch.randn(1, 4)
    a = d(e, torch.tensor([0.1]), torch.tensor([[0.3]]))  # time code fixed: only the gate differs
    b = d(e, torch.tensor([0.4]), torch.tensor([[0.3]]))
    torch.testing.assert_close(a / math.tanh(0.1 / 0.2), b / math.tanh(0.4 / 0.2))


# ---- Θs -------------------------------------------------------------------------------------------


def test_canonical_mlp_shapes_and_colour_range():
    torch.manual_seed(0)
    c = CanonicalMLP(embed_dim=8, time_dim=0, hidden_dim=16, num_hidden=3)
    assert sum(isinstance(m, torch.nn.Linear) for m in c.trunk) == 3
    sdf, rgb = c(torch.randn(5, 8) * 100, None)
    assert sdf.shape == (5,) and rgb.shape == (5, 3)
    assert (rgb >= 0).all() and (rgb <= 1).all()


# ---- the field --------------------------------------------------------------------------------------


def test_field_offset_zero_at_tau_zero_and_nonzero_after():
    field = small_field()
    randomise_output_layer(field.deformation)
    pts = inside_points(40)
    out0 = field(pts, torch.zeros(40))
    assert out0.valid.all()
    assert (out0.offset_sq == 0).all()
    out1 = field(pts, torch.full((40,), 0.5))
    assert (out1.offset_sq > 0).all()
    assert not torch.allclose(out0.sdf, out1.sdf)  # the offset moves the canonical query
    # with canonical_time off, τ = 0 equals the undeformed static query Θs(e)
    e, _ = field.grid.lookup(pts)
    sdf_static, rgb_static = field.canonical(e, None)
    torch.testing.assert_close(out0.sdf, sdf_static)
    torch.testing.assert_close(out0.rgb, rgb_static)


def test_static_field_ignores_time():
    field = small_field(time=False)
    assert field.deformation is None
    pts = inside_points(30)
    a = field(pts, torch.zeros(30))
    b = field(pts, torch.full((30,), 3.7))
    torch.testing.assert_close(a.sdf, b.sdf, rtol=0, atol=0)
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=0)
    assert (a.offset_sq == 0).all() and (b.offset_sq == 0).all()


def test_invalid_points_get_free_sdf_and_black_colour():
    field = small_field()
    randomise_output_layer(field.deformation)
    pts = torch.cat([inside_points(5), torch.tensor([[5.0, 5.0, 5.0], [float("nan"), 0.0, 0.0], [-0.15, 0.0, 0.0]])])
    out = field(pts, torch.full((8,), 0.5))
    assert isinstance(out, FieldOutputs)
    assert out.valid.tolist() == [True] * 5 + [False] * 3
    assert (out.sdf[5:] == 1).all() and (out.rgb[5:] == 0).all() and (out.offset_sq[5:] == 0).all()
    assert torch.isfinite(out.sdf).all() and torch.isfinite(out.rgb).all()
    # the valid entries land at their own positions (masked_scatter order)
    single = field(pts[2:3], torch.full((1,), 0.5))
    torch.testing.assert_close(out.sdf[2:3], single.sdf)


def test_field_with_no_valid_point():
    field = small_field()
    out = field(torch.full((4, 3), 10.0), torch.zeros(4))
    assert not out.valid.any() and (out.sdf == 1).all() and (out.rgb == 0).all()


def test_gradients_reach_embeddings_and_both_mlps():
    field = small_field()
    randomise_output_layer(field.deformation)
    pts = inside_points(64)
    out = field(pts, torch.full((64,), 0.4))
    loss = out.sdf.pow(2).mean() + out.rgb.mean() + out.offset_sq.mean()
    loss.backward()
    assert field.grid.embeddings.grad is not None and field.grid.embeddings.grad.abs().sum() > 0
    for name, module in (("deformation", field.deformation), ("canonical", field.canonical)):
        for pname, p in module.named_parameters():
            assert p.grad is not None and p.grad.abs().sum() > 0, f"{name}.{pname} got no gradient"


def test_gradient_reaches_deformation_through_sdf_alone():
    """Θd is trained by the rendering losses, not only by the offset regulariser."""
    field = small_field()
    randomise_output_layer(field.deformation)
    out = field(inside_points(64), torch.full((64,), 0.4))
    out.sdf.sum().backward()
    assert field.deformation.out.weight.grad.abs().sum() > 0
    assert field.deformation.trunk[0].weight.grad.abs().sum() > 0


def test_canonical_time_input_is_optional():
    field = small_field(canonical_time=True)
    assert field.canonical.trunk[0].in_features == 8 + 9
    assert small_field(canonical_time=False).canonical.trunk[0].in_features == 8
    assert small_field(time=False, canonical_time=True).canonical.trunk[0].in_features == 8
