"""Joint map / window-pose optimisation and the final pass (tivne/slam/mapping.py)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tivne.config import KeyframeConfig, LossWeights, MappingConfig, RenderConfig, SamplerConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import backproject_depth, invert_pose, se3_exp
from tivne.morphology import edge_band
from tivne.render.losses import slam_loss
from tivne.render.rays import View
from tivne.render.renderer import render_pixels
from tivne.render.samplers import PixelPool, PixelSampler, draw
from tivne.slam.keyframes import KeyframePolicy, KeyframeStore
from tivne.slam.mapping import Mapper, final_pass


def make_field(frame, K, seed: int = 0, capacity: int = 4096, columns: slice = slice(None)) -> TimeVaryingField:
    """A field with voxels allocated around frame's depth (only the given image columns)."""
    torch.manual_seed(seed)
    field = TimeVaryingField(time=True, voxel_size=0.1, embed_dim=16, capacity=capacity, hidden_dim=32)
    depth = torch.zeros_like(frame.depth)
    depth[:, columns] = frame.depth[:, columns]
    field.grid.allocate(backproject_depth(depth, K)[depth > 0], dilation=1)
    return field


def fixed_loss(field: TimeVaryingField, view: View, K: torch.Tensor, n: int = 1024) -> float:
    """Loss on a fixed pixel set with deterministic samples (comparable before / after)."""
    pool = PixelPool.from_masks(view.depth > 0, None)
    pixels = draw(pool.valid, n, torch.Generator().manual_seed(123))
    r = RenderConfig()
    with torch.no_grad():
        batch = render_pixels(field, [view], [pixels], view.pose[None], K, r, stratified=False)
        loss, _ = slam_loss(batch, r.truncation, LossWeights())
    return float(loss)


@pytest.fixture(scope="module")
def frames(tiny_cube):
    K = tiny_cube.intrinsics.K()
    f0, f1 = tiny_cube[0], tiny_cube[1]
    # SLAM world frame = first camera: frame 1's pose relative to frame 0
    rel = (invert_pose(f0.gt_pose) @ f1.gt_pose).float()
    v0 = View(0, 0.0, f0.rgb, f0.depth, f0.mask, torch.eye(4))
    v1 = View(1, float(f1.timestamp - f0.timestamp), f1.rgb, f1.depth, f1.mask, rel)
    return v0, v1, K, f0


def test_mapper_run_reduces_loss(frames):
    v0, _, K, f0 = frames
    field = make_field(f0, K)
    mapper = Mapper(field, MappingConfig(rays=512), PixelSampler(), RenderConfig(), LossWeights())
    before = fixed_loss(field, v0, K)
    poses, stats = mapper.run([v0], [True], 40, K, torch.Generator().manual_seed(0))
    after = fixed_loss(field, v0, K)
    assert after < 0.5 * before, (before, after)
    assert stats["skipped_steps"] == 0 and {"total", "color", "depth", "free_space", "sdf", "offset"} <= set(stats)
    torch.testing.assert_close(poses, torch.eye(4)[None])


def test_mapping_draws_no_ray_from_the_motion_mask_edge(frames):
    v0, _, K, f0 = frames
    assert v0.dynamic is not None and bool(v0.dynamic.any())
    band = edge_band(v0.dynamic, 1).reshape(-1)
    drawn: list[torch.Tensor] = []

    class Recording(PixelSampler):
        def __call__(self, pool, n, generator=None):
            drawn.append(super().__call__(pool, n, generator))
            return drawn[-1]

    for edge in (1, 0):
        drawn.clear()
        sampler = Recording(SamplerConfig(dynamic_share=0.3, mask_edge=edge))
        Mapper(make_field(f0, K), MappingConfig(rays=512), sampler, RenderConfig(), LossWeights()).run([v0], [True], 4, K, torch.Generator().manual_seed(0))
        assert bool(band[torch.cat(drawn)].any()) == (edge == 0)  # 0: the band is drawn from like any pixel


@pytest.mark.parametrize("threads", [1, None])
def test_mapping_steps_run_on_the_configured_threads(frames, monkeypatch, threads):
    import tivne.slam.mapping as mapping

    v0, _, K, f0 = frames
    seen, render = [], mapping.render_pixels
    monkeypatch.setattr(mapping, "render_pixels", lambda *a, **k: (seen.append(torch.get_num_threads()), render(*a, **k))[1])
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        mapper = Mapper(make_field(f0, K), MappingConfig(rays=64, threads=threads), PixelSampler(), RenderConfig(), LossWeights())
        mapper.run([v0], [True], 3, K, torch.Generator().manual_seed(0))
        assert seen == [threads or 2] * 3 and torch.get_num_threads() == 2  # the caller's count is back
    finally:
        torch.set_num_threads(before)


def test_fixed_view_pose_unchanged_and_movable_view_refined(frames):
    v0, v1, K, f0 = frames
    field = make_field(f0, K)
    mapper = Mapper(field, MappingConfig(rays=512, optimize_poses=True, lr_pose=1e-3), PixelSampler(), RenderConfig(), LossWeights())
    start1 = se3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.0, 0.0])) @ v1.pose  # a slightly wrong keyframe pose
    v1_off = View(1, v1.tau, v1.rgb, v1.depth, v1.dynamic, start1)
    poses, _ = mapper.run([v1_off, v0], [False, True], 10, K, torch.Generator().manual_seed(0))
    assert poses.shape == (2, 4, 4)
    assert torch.equal(poses[1], v0.pose)  # the fixed (first) view is exactly where it was
    assert (poses[0] - start1).abs().max() > 1e-4  # the movable one was optimised
    torch.testing.assert_close(poses[0, :3, :3] @ poses[0, :3, :3].T, torch.eye(3), atol=1e-5, rtol=0)
    # inputs are not modified in place
    assert torch.equal(v0.pose, torch.eye(4)) and torch.equal(v1_off.pose, start1)


def test_poses_not_optimised_by_default(frames):
    v0, v1, K, f0 = frames
    field = make_field(f0, K)
    poses, _ = Mapper(field, MappingConfig(rays=256), PixelSampler(), RenderConfig(), LossWeights()).run([v1, v0], [False, True], 3, K, torch.Generator().manual_seed(0))
    torch.testing.assert_close(poses, torch.stack([v1.pose, v0.pose]), atol=1e-6, rtol=0)


def test_grid_growth_keeps_adam_state_aligned(frames):
    v0, v1, K, f0 = frames
    field = make_field(f0, K, capacity=64, columns=slice(0, 20))  # the left quarter of the image only
    grid = field.grid
    assert grid.capacity == grid.num_corners  # grown exactly to what was needed: the next voxels grow it
    mapper = Mapper(field, MappingConfig(rays=256), PixelSampler(), RenderConfig(), LossWeights())
    mapper.run([v0], [True], 3, K, torch.Generator().manual_seed(0))
    state = mapper.optimizer.state[grid.embeddings]
    assert state["exp_avg"].shape == grid.embeddings.shape
    old_rows = grid.capacity
    old_avg = state["exp_avg"].clone()
    old_sq = state["exp_avg_sq"].clone()
    # the whole frame now: the voxels of the other three quarters need rows beyond the capacity
    assert grid.allocate(backproject_depth(v0.depth, K)[v0.depth > 0], dilation=1) > 0
    assert grid.capacity > old_rows
    state = mapper.optimizer.state[grid.embeddings]
    for key, old in (("exp_avg", old_avg), ("exp_avg_sq", old_sq)):
        assert state[key].shape == grid.embeddings.shape, key
        assert torch.equal(state[key][:old_rows], old)
        assert (state[key][old_rows:] == 0).all()
    # and optimisation goes on over the grown table (no shape mismatch inside Adam) ...
    mapper.run([v0], [True], 2, K, torch.Generator().manual_seed(1))
    assert mapper.optimizer.state[grid.embeddings]["exp_avg"].shape == grid.embeddings.shape
    # ... and a gradient on the new rows moves them through the same optimiser
    before = grid.embeddings.detach().clone()
    mapper.optimizer.zero_grad(set_to_none=True)
    grid.embeddings.grad = torch.zeros_like(grid.embeddings)
    grid.embeddings.grad[old_rows:] = 1.0
    mapper.optimizer.step()
    moved = (grid.embeddings.detach() - before)[old_rows:]
    assert (moved < 0).all()  # a descent step on every new row


def test_final_pass_revisits_every_view_in_windows_and_never_moves_poses(frames):
    v0, v1, K, f0 = frames
    field = make_field(f0, K)
    mapper = Mapper(field, MappingConfig(rays=128, iters=2, final_iters=7, final_window=1), PixelSampler(), RenderConfig(), LossWeights())
    mapper.steps = 1000  # as if mapping had run 1000 steps online: 10 % of them is over the cap of 7
    seen: list[int] = []
    run = mapper.run

    def spy(views, fixed, iters, *args, **kwargs):
        assert all(fixed) and len(views) == 1 and 1 <= iters <= 2
        seen.extend(v.frame_id for v in views)
        return run(views, fixed, iters, *args, **kwargs)

    mapper.run = spy
    terms = final_pass(mapper, [v0, v1], K, torch.Generator().manual_seed(0))
    assert len(seen) == 4 and sorted(seen[:2]) == [0, 1] and sorted(seen[2:]) == [0, 1]  # 2+2+2+1 steps
    assert "total" in terms
    assert final_pass(Mapper(field, MappingConfig(final_iters=0), PixelSampler(), RenderConfig(), LossWeights()), [v0], K) == {}
    # the budget is final_share of the online steps: 30 steps online -> 3 steps
    seen.clear()
    mapper.steps = 30
    final_pass(mapper, [v0, v1], K, torch.Generator().manual_seed(0))
    assert len(seen) == 2  # rounds of 2 + 1 steps


def test_the_first_frame_runs_first_now_steps_and_the_next_rounds_the_rest(frames):
    v0, v1, K, f0 = frames
    cfg = MappingConfig(rays=64, iters=4, first_iters=11, first_now=3)
    mapper = Mapper(make_field(f0, K), cfg, PixelSampler(), RenderConfig(), LossWeights())
    store, policy, gen = KeyframeStore(KeyframeConfig()), KeyframePolicy(KeyframeConfig()), torch.Generator().manual_seed(0)
    store.add(v0)
    steps = []
    for k, first in ((0, True), (1, False), (2, False), (3, False)):
        before = mapper.steps
        mapper.map_frame(v0 if first else v1, store, policy, K, gen, first=first)
        steps.append(mapper.steps - before)
        if k == 1:  # a restored mapper owes what the saved one did
            fresh = Mapper(mapper.field, cfg, PixelSampler(), RenderConfig(), LossWeights())
            fresh.load_state_dict(mapper.state_dict())
            assert fresh.owed == mapper.owed == 4
    assert steps == [3, 8, 8, 4] and sum(steps) == cfg.first_iters + 3 * cfg.iters


def test_explained_share_counts_rays_within_tolerance():
    from data_modules.sensor import kinect_depth_sigma
    from tivne.slam.mapping import explained_share

    measured = torch.tensor([1.0, 2.0, 3.0, 4.0])
    sigma = kinect_depth_sigma(measured)  # the residual a perfect map leaves grows with depth
    assert explained_share(measured + sigma * torch.tensor([0.0, 2.9, -2.9, 3.1]), measured, 3.0) == 0.75
    assert explained_share(measured + 0.02, measured, 3.0) == 0.5  # 2 cm is noise at 3-4 m, not at 1-2 m
    assert explained_share(torch.zeros(0), torch.zeros(0), 3.0) == 1.0


def test_a_settling_round_stops_early_only_where_the_map_explains_the_frame(frames):
    """A fresh map explains nothing (the whole round runs); after fitting the same view, its depth
    renders within the tolerance and the next settling round stops after settle_iters steps."""
    v0, _, K, f0 = frames
    cfg = MappingConfig(rays=512, settle_share=0.8, settle_iters=3)
    mapper = Mapper(make_field(f0, K), cfg, PixelSampler(), RenderConfig(), LossWeights())
    _, fresh = mapper.run([v0], [True], 10, K, torch.Generator().manual_seed(0), settle=True)
    assert fresh["steps"] == 10
    mapper.run([v0], [True], 60, K, torch.Generator().manual_seed(1))
    _, settled = mapper.run([v0], [True], 10, K, torch.Generator().manual_seed(2), settle=True)
    assert settled["steps"] == 3
    _, unsettled = mapper.run([v0], [True], 10, K, torch.Generator().manual_seed(2))  # settle off: every step
    assert unsettled["steps"] == 10 and mapper.steps == 10 + 60 + 3 + 10


def test_a_frame_without_moving_pixels_gets_static_iters_steps(frames):
    v0, v1, K, f0 = frames
    assert v1.dynamic is not None and bool(v1.dynamic.any())  # the tiny cube moves in view
    cfg = MappingConfig(rays=64, iters=4, static_iters=2, first_iters=0, first_now=0)
    mapper = Mapper(make_field(f0, K), cfg, PixelSampler(), RenderConfig(), LossWeights())
    store, policy, gen = KeyframeStore(KeyframeConfig()), KeyframePolicy(KeyframeConfig()), torch.Generator().manual_seed(0)
    store.add(v0)
    steps = []
    for view in (v1, dataclasses.replace(v1, dynamic=None), dataclasses.replace(v1, dynamic=torch.zeros_like(v1.dynamic))):
        before = mapper.steps
        mapper.map_frame(view, store, policy, K, gen, first=False)
        steps.append(mapper.steps - before)
    assert steps == [cfg.iters, cfg.static_iters, cfg.static_iters]
