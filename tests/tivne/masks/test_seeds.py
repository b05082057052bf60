"""Seeds of the geometric masks (tivne.masks.seeds): against the map's depth and against an earlier frame."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from data_modules.frame import Intrinsics
from tivne.masks.seeds import free_space_seeds, residual_seeds

sys.path.insert(0, str(Path(__file__).parent))
from mask_scenes import H, W, box_depth, scene_depth, square  # noqa: E402


def test_residual_seeds_sign_and_known_space():
    old, new = square(10, 10, 12), square(10, 16, 12)
    observed, rendered = scene_depth(new), scene_depth(old)
    known = torch.ones(H, W, dtype=torch.bool)
    seeds = residual_seeds(observed, rendered, known)
    # Only the object's current pixels where the map had background: not the disoccluded strip.
    assert torch.equal(seeds, new & ~old)
    unknown = known.clone()
    unknown[:, 20:] = False
    assert not (residual_seeds(observed, rendered, unknown)[:, 20:]).any()
    noisy = rendered + 0.01 * torch.randn(H, W)  # within k·σ(z)
    assert not residual_seeds(noisy, rendered, known).any()


def test_free_space_seeds_against_an_earlier_frame_with_camera_motion():
    K = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H).K()
    before_d, before = box_depth(K, -0.5, -0.1, -0.3, 0.1, 1.5)
    now_d, now = box_depth(K, -0.3, 0.1, -0.3, 0.1, 1.5)
    seeds, known, _ = free_space_seeds(now_d, torch.eye(4), before_d, torch.eye(4), K)
    # the object's new pixels (less one pixel next to the old place, from the 3x3 min); not the
    # disoccluded wall
    grown = torch.nn.functional.max_pool2d(before[None, None].float(), 3, 1, 1)[0, 0] > 0
    assert not (seeds & ~(now & ~before)).any() and not ((now & ~grown) & ~seeds).any()
    # A static scene seen from a moved camera: nothing fires (3x3 min keeps silhouettes quiet).
    pose = torch.eye(4)
    pose[0, 3] = 0.05
    ref_d, _ = box_depth(K, -0.55, -0.15, -0.3, 0.1, 1.5)  # the same scene from the moved camera
    seeds, known, _ = free_space_seeds(before_d, torch.eye(4), ref_d, pose, K)
    assert known.float().mean() > 0.8 and seeds.sum() <= 2
