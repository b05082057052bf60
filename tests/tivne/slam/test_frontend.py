"""The tracking front end (tivne/slam/frontend.py): odometry against a reference, loss detection."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from data_modules.frame import Frame
from data_modules.synthetic import SyntheticSequence
from tivne.config import LossWeights, OdometryConfig, RenderConfig, TrackingConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import invert_pose, se3_exp
from tivne.render.rays import View
from tivne.slam.frontend import Tracker, pose_jump
from tivne.train import build_system

CONF = Path(__file__).resolve().parents[3] / "conf"
W, H = 160, 120


@pytest.fixture(scope="module")
def room() -> SyntheticSequence:
    return SyntheticSequence("static_room", num_frames=8, width=W, height=H, depth_noise=False, rgb_noise=0.0, cache_dir=None)


def view_at(seq: SyntheticSequence, c2w: torch.Tensor, frame_id: int) -> View:
    rgb, depth, _ = seq.render_at(c2w, 0.0)
    return View(frame_id, 0.0, rgb, depth, None, torch.eye(4))


def relative(seq: SyntheticSequence, i: int) -> torch.Tensor:
    """GT pose of frame i in the first camera's frame (the SLAM world frame), float32."""
    return (invert_pose(seq.camera_pose(0)) @ seq.camera_pose(i)).float()


def make_tracker(method: str = "odometry", **kw) -> Tracker:
    return Tracker(TrackingConfig(method=method, **kw), OdometryConfig(), RenderConfig(), LossWeights())


def test_odometry_tracks_against_the_reference_and_switches_it(room):
    tracker = make_tracker(reference="adaptive")
    K = room.intrinsics.K()
    first = view_at(room, room.camera_pose(0), 0)
    first.pose = torch.eye(4)
    assert tracker.update_reference(first, K, {}, is_keyframe=True) and tracker.reference.frame_id == 0
    poses = [torch.eye(4)]
    for i in range(1, 4):
        result = tracker.track(TimeVaryingField(), view_at(room, room.camera_pose(i), i), poses, K, None)
        t_err, r_err = pose_jump(result.pose, relative(room, i))
        assert not result.lost and t_err < 2e-3 and r_err < 0.1, (i, t_err, r_err, result.stats)
        assert result.stats["odo_ok"] == 1.0 and result.stats["odo_inlier_ratio"] > 0.9
        poses.append(result.pose)
    # adaptive: a well-overlapping frame does not become the reference; a poor overlap does
    assert not tracker.update_reference(View(3, 0.0, first.rgb, first.depth, None, poses[-1]), K, {"odo_overlap": 0.9, "odo_inlier_ratio": 0.9}, False)
    assert tracker.update_reference(View(3, 0.0, first.rgb, first.depth, None, poses[-1]), K, {"odo_overlap": 0.5}, False)


def test_a_frame_that_jumps_is_lost_and_keeps_the_prediction_not_identity(room):
    tracker = make_tracker()
    K = room.intrinsics.K()
    first = view_at(room, room.camera_pose(0), 0)
    first.pose = torch.eye(4)
    tracker.update_reference(first, K, {}, is_keyframe=True)
    poses = [torch.eye(4), relative(room, 1)]
    # the camera turned 120 degrees between two frames: nothing overlaps the reference
    turned = room.camera_pose(1) @ se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(120.0), 0.0], dtype=torch.float64))
    result = tracker.track(TimeVaryingField(), view_at(room, turned, 2), poses, K, None)
    assert result.lost and result.stats["lost"] == 1.0 and result.stats["jump_deg"] > 30 and not result.recovered
    predicted = poses[-1] @ invert_pose(poses[-2]) @ poses[-1]
    assert torch.allclose(result.pose, predicted, atol=1e-5)  # the motion model's guess, flagged
    assert not torch.allclose(result.pose, torch.eye(4), atol=1e-3)


def test_field_tracker_alone_reports_loss_by_inlier_ratio(room):
    tracker = make_tracker("field", iters=2, rays=64)
    v = view_at(room, room.camera_pose(1), 1)
    field = TimeVaryingField(voxel_size=0.2, capacity=512, hidden_dim=16)  # an empty map: no ray renders
    result = tracker.track(field, v, [torch.eye(4)], room.intrinsics.K(), torch.Generator().manual_seed(0))
    assert result.lost and result.stats["field_inlier_ratio"] == 0.0
    assert torch.equal(result.pose, torch.eye(4))  # the prediction (zero motion from one pose), flagged lost


def smoke_system(tmp_path, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", "output.save_every=0", *overrides])
    return build_system(cfg, SyntheticSequence("cube", num_frames=6, width=80, height=60, cache_dir=None).intrinsics, tmp_path)


def test_frames_without_static_depth_are_counted_warned_and_never_mapped(tmp_path, tiny_cube, capsys):
    system = smoke_system(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k in range(3):
            system.training_step(tiny_cube[k], k)
        voxels = system.field.grid.num_voxels
        hits = system.field.grid.voxel_hits.clone()
        blank = dataclasses.replace(tiny_cube[3], depth=torch.zeros_like(tiny_cube[3].depth))
        system.training_step(blank, 3)
    assert system.counts.without_tracking == 1 and system.field.grid.num_voxels == voxels
    assert torch.equal(system.field.grid.voxel_hits, hits)  # nothing allocated or counted from it
    err = capsys.readouterr().err
    assert "warning: frame 3" in err and "not tracked, not mapped" in err
    metrics = system.run_metrics()
    assert metrics["frames_without_tracking"] == 1 and metrics["tracking_lost"] == 0
    assert len(system.trajectory) == 4 and not torch.allclose(system.poses()[3], torch.eye(4, dtype=torch.float64))


def test_every_method_runs_in_the_loop(tmp_path, tiny_cube):
    for method in ("odometry", "odometry+field", "field"):
        system = smoke_system(tmp_path / method, f"tracking.method={method}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for k in range(4):
                system.training_step(tiny_cube[k], k)
        gt = [invert_pose(tiny_cube[0].gt_pose) @ tiny_cube[k].gt_pose for k in range(4)]
        err = max(pose_jump(system.poses()[k], gt[k])[0] for k in range(4))
        assert err < 0.03, (method, err)  # smoke settings: 3 field iterations
        assert isinstance(tiny_cube[0], Frame)
