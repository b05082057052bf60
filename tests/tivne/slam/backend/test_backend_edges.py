"""Edge candidates and pyramids of the pose graph (tivne/slam/backend/edges.py)."""

from __future__ import annotations

import math

import torch

from data_modules.synthetic import SyntheticSequence
from tivne.config import BackendConfig, OdometryConfig
from tivne.geometry import se3_exp
from tivne.render.rays import View
from tivne.slam.backend.edges import covisible_candidates, keyframe_pyramid, loop_candidates


def twist(v, w_deg) -> torch.Tensor:
    return se3_exp(torch.tensor([*v, *(math.radians(a) for a in w_deg)], dtype=torch.float64))


def views_along(seq: SyntheticSequence, yaws: list[float]) -> list[View]:
    P0 = seq.camera_pose(0)
    out = []
    for k, yaw in enumerate(yaws):
        P = P0 @ twist((0, 0, 0), (0, yaw, 0))
        rgb, depth, labels = seq.render_at(P, 0.0)
        out.append(View(5 * k, 0.0, rgb, depth, labels > 0, P.float()))
    return out


def test_masked_pixels_never_enter_an_edge(tiny_cube):
    """The keyframe pyramid drops the dynamic mask's pixels at every level (no edge can use them)."""
    rgb, depth, labels = tiny_cube.render_at(tiny_cube.camera_pose(0), 0.0)
    mask = labels > 0
    assert mask.any()
    pyramid = keyframe_pyramid(View(0, 0.0, rgb, depth, mask, tiny_cube.camera_pose(0).float()), tiny_cube.intrinsics.K(), OdometryConfig(), BackendConfig())
    assert not (pyramid[0].usable & mask).any() and (pyramid[0].depth[mask] == 0).all()
    assert len(pyramid) == OdometryConfig().levels + BackendConfig().loop_extra_levels


def test_candidates_by_overlap_and_pose(tiny_cube):
    """Co-visible: the predecessor plus overlapping recent keyframes; loops: old keyframes near in
    pose and overlapping, never one looking away."""
    yaws = [0, 5, 10, 15, 90, 95, 100, 105, 2]
    views = views_along(tiny_cube, yaws)
    cfg = BackendConfig(covisible=2, loop_min_gap=4, min_overlap=0.5)
    K = tiny_cube.intrinsics.K()
    new, earlier = views[-1], views[:-1]
    cov = covisible_candidates(earlier, new, K, cfg)
    assert cov[-1] == len(earlier) - 1  # the predecessor always
    assert all(i >= len(earlier) - cfg.loop_min_gap for i in cov)
    loops = loop_candidates(earlier, new, K, BackendConfig(loop_min_gap=4, loop_candidates=2))
    assert loops and set(loops) <= {0, 1, 2, 3}  # the views at 0-15°, not the ones at 90-105°
