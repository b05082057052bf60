"""Reprojection overlap between views (tivne/slam/tracking/overlap.py); overlap_ratios itself is
tested with the keyframe policy that uses it (tests/tivne/slam/test_keyframes.py)."""

from __future__ import annotations

import math

import torch

from tivne.geometry import se3_exp
from tivne.render.rays import View
from tivne.slam.tracking.overlap import view_overlaps, views_seeing

W, H = 40, 30
K = torch.tensor([[30.0, 0.0, 20.0], [0.0, 30.0, 15.0], [0.0, 0.0, 1.0]])


def wall_view(dynamic: torch.Tensor | None = None) -> View:
    """A camera at the origin looking at a wall 2 m away (every pixel has depth)."""
    return View(0, 0.0, torch.zeros(H, W, 3), torch.full((H, W), 2.0), dynamic, torch.eye(4))


def slid(x: float) -> torch.Tensor:
    return se3_exp(torch.tensor([x, 0.0, 0.0, 0.0, 0.0, 0.0]))


def turned(degrees: float) -> torch.Tensor:
    return se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(degrees), 0.0]))


def test_view_overlaps_counts_the_static_pixels_another_camera_sees():
    # the wall is 2 * 2 * 20 / 30 = 2.67 m wide at 2 m: a camera slid by half of that sees half of it
    ratios = view_overlaps(wall_view(), [torch.eye(4), slid(4.0 / 3.0), slid(10.0)], K)
    assert torch.allclose(ratios, torch.tensor([1.0, 0.5, 0.0]), atol=0.06)
    left = torch.zeros(H, W, dtype=torch.bool)
    left[:, : W // 2] = True  # the left half is moving: only the right half counts, and a camera slid right sees all of it
    assert float(view_overlaps(wall_view(left), [slid(4.0 / 3.0)], K)[0]) > 0.95
    assert view_overlaps(wall_view(torch.ones(H, W, dtype=torch.bool)), [torch.eye(4)], K).tolist() == [0.0]
    assert view_overlaps(wall_view(), [], K).numel() == 0
    doubled = view_overlaps(wall_view(), [slid(4.0 / 3.0).double()], K.double())  # poses of another dtype are fine
    assert torch.allclose(doubled, ratios[1:2], atol=1e-6)


def test_views_seeing_needs_pose_and_overlap_and_keeps_the_order():
    stored = [turned(40.0), turned(-4.0), turned(0.0), turned(2.0), slid(0.3)]
    seeing = views_seeing(wall_view(), stored, K, 0.1, 15.0, 0.85)
    assert [i for i, _ in seeing] == [1, 2, 3]  # 40 degrees turned and 30 cm slid: out; the rest in order
    assert all(r >= 0.85 for _, r in seeing) and dict(seeing)[2] == 1.0
    assert views_seeing(wall_view(), stored[1:4], K, 0.1, 15.0, 1.01) == []  # the overlap bar not met
    assert [i for i, _ in views_seeing(wall_view(), stored, K, math.inf, 15.0, 0.0)] == [1, 2, 3, 4]  # no distance gate
    assert views_seeing(wall_view(), [], K, 0.1, 15.0, 0.0) == []
