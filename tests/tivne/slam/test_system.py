"""TivNeSLAM driven frame by frame without a Trainer (tivne/slam/system.py)."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from data_modules.tables import read_tum_trajectory
from tivne.slam.mapping import final_pass
from tivne.train import build_system

CONF = Path(__file__).resolve().parents[3] / "conf"


def smoke_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", *overrides])


@pytest.fixture(scope="module")
def processed(tiny_cube, tmp_path_factory):
    """A system fed the tiny cube's first 5 frames by hand (keyframe every 2 frames)."""
    torch.manual_seed(0)
    run_dir = tmp_path_factory.mktemp("system")
    cfg = smoke_cfg("keyframe.every=2", "output.save_every=0")
    system = build_system(cfg, tiny_cube.intrinsics, run_dir)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log without a Trainer
        for k in range(5):
            system.training_step(tiny_cube[k], k)
    return system, run_dir, tiny_cube


def test_first_pose_is_identity_and_one_record_per_frame(processed):
    system, _, cube = processed
    traj = system.poses()
    assert traj.shape == (5, 4, 4) and traj.dtype == torch.float64
    torch.testing.assert_close(traj[0], torch.eye(4, dtype=torch.float64))
    assert system.trajectory.timestamps() == [float(cube[k].timestamp) for k in range(5)]
    assert system.db.frame_ids() == [0, 2, 4]
    assert len(system.timers.per_frame) == 5
    assert system.field.grid.num_voxels > 0
    R = traj[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-5, rtol=0)


def test_tracked_trajectory_follows_ground_truth(processed):
    system, _, _ = processed
    est = system.poses()
    gt = torch.stack([r.gt_pose for r in system.trajectory.records]).double()
    # relative motion of the first to last frame, compared in the first camera's frame
    gt_rel = torch.linalg.inv(gt[0]) @ gt
    err = (est[:, :3, 3] - gt_rel[:, :3, 3]).norm(dim=-1)
    assert float(err.max()) < 0.05
    result = system.trajectory.ate(system.keyframe_poses())
    assert result is not None and math.isfinite(float(result.rmse)) and float(result.rmse) < 0.05


def test_trajectory_follows_keyframe_refinement(processed):
    system, _, _ = processed
    before = system.poses()
    kf = system.db.views[1]  # frame 2
    old = kf.pose.clone()
    try:
        shift = torch.eye(4)
        shift[0, 3] = 0.1
        kf.pose = shift @ old
        after = system.poses()
        # frames recorded against keyframe 1 (frames 2, 3) move with it; the others do not
        torch.testing.assert_close(after[2:4, 0, 3], before[2:4, 0, 3] + 0.1, atol=1e-5, rtol=0)
        torch.testing.assert_close(after[[0, 1, 4]], before[[0, 1, 4]])
    finally:
        kf.pose = old


def test_finalize_writes_run_outputs(processed):
    system, run_dir, _ = processed
    metrics = system.finalize()
    ts, poses = read_tum_trajectory(run_dir / "trajectory.txt")
    assert len(ts) == 5 and poses.shape == (5, 4, 4)
    assert (run_dir / "checkpoints" / "slam.pt").is_file()
    on_disk = json.loads((run_dir / "metrics.json").read_text())
    assert on_disk["frames"] == 5 and metrics["frames"] == 5
    assert math.isfinite(on_disk["s_per_frame"]) and on_disk["s_per_frame"] > 0
    assert on_disk["keyframes"] == 3 and on_disk["voxels"] == system.field.grid.num_voxels
    assert on_disk["ate_rmse_m"] is not None


def test_final_pass_cycles_through_every_keyframe_with_fixed_poses(processed, monkeypatch):
    import dataclasses

    system, _, _ = processed
    calls = []
    real_run = system.mapper.run

    def recording_run(views, fixed, iters, *args, **kwargs):
        calls.append(([v.frame_id for v in views], list(fixed), iters, kwargs.get("current_share")))
        return real_run(views, fixed, iters, *args, **kwargs)

    monkeypatch.setattr(system.mapper, "run", recording_run)
    monkeypatch.setattr(system.mapper, "cfg", dataclasses.replace(system.mapping_cfg, iters=3, final_iters=8, final_share=10.0, final_window=2))
    poses = [v.pose.clone() for v in system.db.views]
    args = (system.K, system.sampler, system.render_cfg, system.loss_weights, system.generator)
    terms = final_pass(system.mapper, list(system.db.views), *args)
    assert [c[2] for c in calls] == [3, 3, 2]  # 8 steps in rounds of mapping.iters
    for ids, fixed, _, share in calls:  # distinct keyframes per window, poses fixed, rays split evenly
        assert len(set(ids)) == 2 and all(fixed) and share == 0.5
    visited = [i for c in calls for i in c[0]]
    assert set(visited[:3]) == {0, 2, 4}  # a shuffled cycle: all keyframes before any repeats
    assert all(torch.equal(v.pose, p) for v, p in zip(system.db.views, poses))
    assert math.isfinite(terms["total"])

    calls.clear()
    monkeypatch.setattr(system.mapper, "cfg", dataclasses.replace(system.mapping_cfg, final_iters=0))
    assert final_pass(system.mapper, list(system.db.views), *args) == {} and calls == []
