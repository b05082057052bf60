"""Motion model, map freezing and pose tracking against a fitted map (tivne/slam/tracking/field.py)."""

from __future__ import annotations

import math

import pytest
import torch

from tivne.config import FieldTrackingConfig, LossWeights, MappingConfig, RenderConfig, TrackingConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import backproject_depth, invert_pose, se3_exp
from tivne.render.rays import View
from tivne.render.samplers import PixelSampler
from tivne.slam.mapping import Mapper
from tivne.slam.tracking.field import frozen, predict_pose, track_frame


def pose_error(T: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """(translation error m, rotation error rad) of T against ref."""
    D = invert_pose(ref) @ T
    cos = ((D[:3, :3].trace() - 1) / 2).clamp(-1, 1)
    return float(D[:3, 3].norm()), float(torch.arccos(cos))


def twist(seed: int, trans: float, rot: float) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    xi = torch.randn(6, generator=gen)
    return torch.cat([xi[:3] / xi[:3].norm() * trans, xi[3:] / xi[3:].norm() * rot])


# ---- motion model -------------------------------------------------------------------------------


def test_predict_pose_zero_motion():
    a, b = se3_exp(twist(0, 0.1, 0.1)), se3_exp(twist(1, 0.1, 0.1))
    out = predict_pose([a, b], "zero")
    torch.testing.assert_close(out, b)
    assert out is not b  # a copy, not the stored pose
    torch.testing.assert_close(predict_pose([a], "constant_velocity"), a)


def test_predict_pose_constant_velocity():
    step = se3_exp(twist(2, 0.05, 0.03))
    T0 = se3_exp(twist(3, 0.5, 0.4))
    T1 = step @ T0
    T2 = predict_pose([T0, T1], "constant_velocity")
    torch.testing.assert_close(T2, step @ step @ T0, atol=1e-5, rtol=0)
    R = T2[:3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3), atol=1e-6, rtol=0)
    # with a still camera the prediction stays put
    torch.testing.assert_close(predict_pose([T0, T0], "constant_velocity"), T0, atol=1e-6, rtol=0)


def test_predict_pose_carries_the_velocity_over_the_time_to_the_frame():
    step = se3_exp(twist(4, 0.02, 0.01))
    T0 = se3_exp(twist(5, 0.5, 0.4))
    T1 = step @ T0
    # three frames dropped: the prediction is four steps on, not one; half an interval: half a step
    torch.testing.assert_close(predict_pose([T0, T1], "constant_velocity", 4.0), step @ step @ step @ step @ T1, atol=1e-5, rtol=0)
    half = predict_pose([T0, T1], "constant_velocity", 0.5)
    torch.testing.assert_close(predict_pose([T1, half], "constant_velocity", 1.0), step @ T1, atol=1e-5, rtol=0)
    torch.testing.assert_close(predict_pose([T0, T1], "zero", 4.0), T1)  # zero motion stays zero


def test_tracking_config_validation():
    with pytest.raises(ValueError, match="field_tracking.query_time"):
        FieldTrackingConfig(query_time="now")
    with pytest.raises(ValueError, match="tracking.motion_model"):
        TrackingConfig(motion_model="linear")


# ---- frozen -------------------------------------------------------------------------------------------


def test_frozen_disables_and_restores_requires_grad():
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 1))
    net[1].bias.requires_grad_(False)  # a mixed state must come back exactly
    before = [p.requires_grad for p in net.parameters()]
    with frozen(net):
        assert not any(p.requires_grad for p in net.parameters())
    assert [p.requires_grad for p in net.parameters()] == before
    with pytest.raises(RuntimeError, match="boom"):
        with frozen(net):
            raise RuntimeError("boom")
    assert [p.requires_grad for p in net.parameters()] == before


# ---- track_frame on a fitted map ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def fitted(tiny_cube):
    """A map fitted for 100 steps to frame 0 of the tiny cube at the identity pose."""
    torch.manual_seed(0)
    frame = tiny_cube[0]
    K = tiny_cube.intrinsics.K()
    field = TimeVaryingField(time=True, voxel_size=0.1, embed_dim=16, capacity=4096, hidden_dim=32)
    field.grid.allocate(backproject_depth(frame.depth, K)[frame.depth > 0], dilation=1)
    view = View(0, 0.0, frame.rgb, frame.depth, frame.mask, torch.eye(4))
    Mapper(field, MappingConfig(rays=512), PixelSampler(), RenderConfig(), LossWeights()).run(
        [view], [True], 100, K, torch.Generator().manual_seed(0)
    )
    return field, frame, K


CFG = FieldTrackingConfig(iters=40, rays=512)


@pytest.mark.parametrize("seed", [0, 1])
def test_track_frame_recovers_small_perturbation(fitted, seed):
    field, frame, K = fitted
    init = se3_exp(twist(seed, 0.02, math.radians(0.9)))
    t0, r0 = pose_error(init, torch.eye(4))
    pose, stats = track_frame(field, View(0, 0.0, frame.rgb, frame.depth, frame.mask, init), K, RenderConfig(), LossWeights(), CFG, torch.Generator().manual_seed(1))
    t1, r1 = pose_error(pose, torch.eye(4))
    assert t1 < 0.7 * t0 and r1 < r0, (t0, r0, t1, r1)
    assert math.isfinite(stats.loss) and stats.nonfinite == 0 and stats.inlier_ratio > 0.9
    torch.testing.assert_close(pose[:3, :3] @ pose[:3, :3].T, torch.eye(3), atol=1e-5, rtol=0)


def test_track_frame_at_true_pose_stays_close(fitted):
    field, frame, K = fitted
    pose, _ = track_frame(field, View(0, 0.0, frame.rgb, frame.depth, frame.mask, torch.eye(4)), K, RenderConfig(), LossWeights(), CFG, torch.Generator().manual_seed(1))
    t, r = pose_error(pose, torch.eye(4))
    assert t < 0.005 and r < math.radians(0.3)


def test_track_frame_gradients_reach_only_the_pose(fitted):
    field, frame, K = fitted
    field.zero_grad(set_to_none=True)
    flags = [p.requires_grad for p in field.parameters()]
    params = [p.detach().clone() for p in field.parameters()]
    init = se3_exp(twist(3, 0.02, 0.01))
    pose, _ = track_frame(field, View(0, 0.0, frame.rgb, frame.depth, frame.mask, init), K, RenderConfig(), LossWeights(), FieldTrackingConfig(iters=5, rays=256), torch.Generator().manual_seed(1))
    assert not torch.allclose(pose, init)  # the pose moved: gradients reached it
    assert all(p.grad is None for p in field.parameters())
    assert [p.requires_grad for p in field.parameters()] == flags and all(flags)
    for p, q in zip(field.parameters(), params):
        assert torch.equal(p.detach(), q)


def test_track_frame_off_the_map_keeps_initial_pose(fitted):
    field, frame, K = fitted
    far = torch.eye(4)
    far[:3, 3] = torch.tensor([50.0, 0.0, 0.0])  # nothing allocated there: no ray hits the map
    pose, stats = track_frame(field, View(0, 0.0, frame.rgb, frame.depth, None, far), K, RenderConfig(), LossWeights(), FieldTrackingConfig(iters=5, rays=64), torch.Generator().manual_seed(0))
    torch.testing.assert_close(pose, far)
    assert torch.isfinite(pose).all()
