"""SlamLoop driven frame by frame without a Trainer (tivne/slam/loop.py), its writer
(tivne/slam/results.py) and the thin LightningModule around it (tivne/slam/system.py)."""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from data_modules.tables import read_tum_trajectory
from tivne.geometry import invert_pose
from tivne.render.rays import View
from tivne.slam.loop import SlamLoop
from tivne.slam.mapping import final_pass
from tivne.slam.results import RunWriter, run_metrics
from tivne.slam.run import TrainSettings, build_system, loop_from_config
from tivne.slam.state import FrameReport
from tivne.slam.tracking import TrackStatus
from tivne.slam.tracking.tracker import pose_jump

CONF = Path(__file__).resolve().parents[3] / "conf"


def smoke_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", "output.save_every=0", *overrides])


def smoke_loop(intrinsics, *overrides: str) -> SlamLoop:
    return loop_from_config(smoke_cfg(*overrides), intrinsics)  # with the config's (dataset) masks


@pytest.fixture(scope="module")
def processed(tiny_cube, tmp_path_factory):
    """A loop fed the tiny cube's first 5 frames by hand (keyframe every 2 frames), and its reports."""
    torch.manual_seed(0)
    run_dir = tmp_path_factory.mktemp("loop")
    cfg = smoke_cfg("keyframe.every=2")
    settings = TrainSettings.from_config(cfg)
    loop = loop_from_config(cfg, tiny_cube.intrinsics)
    reports = [loop.step(tiny_cube[k]) for k in range(5)]
    return loop, RunWriter(run_dir, settings.output, settings.mesh), run_dir, tiny_cube, reports


def test_first_pose_is_identity_and_one_record_per_frame(processed):
    loop, _, _, cube, reports = processed
    traj = loop.poses.all()
    assert traj.shape == (5, 4, 4) and traj.dtype == torch.float64
    torch.testing.assert_close(traj[0], torch.eye(4, dtype=torch.float64))
    assert loop.trajectory.timestamps() == [float(cube[k].timestamp) for k in range(5)]
    assert loop.keyframes.frame_ids() == [0, 2, 4]
    assert len(loop.timers.per_frame) == 5 and loop.field.grid.num_voxels > 0
    R = traj[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-5, rtol=0)
    assert loop.clock.t0 == float(cube[0].timestamp) and loop.clock.tau(cube[3].timestamp) == pytest.approx(reports[3].tau)


def test_reports_are_typed_and_carry_what_the_frame_did(processed):
    loop, _, _, _, reports = processed
    assert all(isinstance(r, FrameReport) for r in reports)
    assert [r.index for r in reports] == list(range(5)) and [r.keyframe for r in reports] == [True, False, True, False, True]
    assert all(r.track.status is TrackStatus.TRACKED and r.mapping is not None for r in reports)  # smoke maps every frame
    assert reports[0].mapping.window == (0,) and reports[3].mapping.window[0] == 3
    scalars = reports[3].scalars()
    assert {"track/odo_inlier_ratio", "track/new_reference", "map/loss", "map/window", "perf/s_per_frame", "map/voxels"} <= set(scalars)
    assert all(isinstance(v, float) and math.isfinite(v) for v in scalars.values())
    assert all(r.view.dynamic is not None and r.view.dynamic.any() for r in reports)  # the cube's dataset masks
    for r in reports:  # the pose recorded is the pose reported: no second copy to drift
        torch.testing.assert_close(loop.poses.pose(r.index), r.pose.double(), atol=1e-6, rtol=0)


def test_tracked_trajectory_follows_ground_truth(processed):
    loop = processed[0]
    est = loop.poses.all()
    gt = torch.stack([r.gt_pose for r in loop.trajectory.records]).double()
    gt_rel = torch.linalg.inv(gt[0]) @ gt  # relative motion, in the first camera's frame
    assert float((est[:, :3, 3] - gt_rel[:, :3, 3]).norm(dim=-1).max()) < 0.05
    result = loop.ate()
    assert result is not None and math.isfinite(float(result.rmse)) and float(result.rmse) < 0.05


def test_the_keyframe_store_alone_owns_keyframe_poses(processed):
    loop = processed[0]
    before = loop.poses.all()
    old = loop.keyframes.pose(2)
    try:
        shift = torch.eye(4)
        shift[0, 3] = 0.1
        loop.keyframes.update_poses({2: shift @ old})
        after = loop.poses.all()
        # frames recorded against keyframe 2 (frames 2, 3) move with it; the others do not
        torch.testing.assert_close(after[2:4, 0, 3], before[2:4, 0, 3] + 0.1, atol=1e-5, rtol=0)
        torch.testing.assert_close(after[[0, 1, 4]], before[[0, 1, 4]])
        assert loop.keyframes.view(1).pose[0, 3] == pytest.approx(float(old[0, 3]) + 0.1)  # mapping sees it too
        # the motion model reads the trajectory: the moved poses are what the next frame predicts from
        torch.testing.assert_close(loop.poses.recent(2)[0], after[3])
    finally:
        loop.keyframes.update_poses({2: old})


def test_keyframe_records_are_frozen_uint8(processed):
    loop = processed[0]
    record = loop.keyframes.records[0]
    assert record.rgb.dtype == torch.uint8 and record.colour().dtype == torch.float32
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.rgb = record.rgb.float()  # type: ignore[misc]
    view = loop.keyframes.view(0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.pose = torch.eye(4)  # type: ignore[misc]


def test_finalize_writes_run_outputs(processed):
    loop, writer, run_dir, _, _ = processed
    metrics = writer.finalize(loop)
    ts, poses = read_tum_trajectory(run_dir / "trajectory.txt")
    assert len(ts) == 5 and poses.shape == (5, 4, 4)
    assert (run_dir / "checkpoints" / "slam.pt").is_file()
    on_disk = json.loads((run_dir / "metrics.json").read_text())
    assert on_disk["frames"] == 5 and metrics["frames"] == 5
    assert math.isfinite(on_disk["s_per_frame"]) and on_disk["s_per_frame"] > 0
    assert on_disk["keyframes"] == 3 and on_disk["voxels"] == loop.field.grid.num_voxels
    assert on_disk["ate_rmse_m"] is not None


def test_final_pass_cycles_through_every_keyframe_with_fixed_poses(processed, monkeypatch):
    loop = processed[0]
    calls = []
    real_run = loop.mapper.run

    def recording_run(views, fixed, iters, *args, **kwargs):
        calls.append(([v.frame_id for v in views], list(fixed), iters, kwargs.get("current_share")))
        return real_run(views, fixed, iters, *args, **kwargs)

    monkeypatch.setattr(loop.mapper, "run", recording_run)
    monkeypatch.setattr(loop.mapper, "cfg", dataclasses.replace(loop.mapper.cfg, iters=3, final_iters=8, final_share=10.0, final_window=2))
    poses = loop.keyframes.poses().clone()
    terms = final_pass(loop.mapper, loop.keyframes.views(), loop.K, loop.generator)
    assert [c[2] for c in calls] == [3, 3, 2]  # 8 steps in rounds of mapping.iters
    for ids, fixed, _, share in calls:  # distinct keyframes per window, poses fixed, rays split evenly
        assert len(set(ids)) == 2 and all(fixed) and share == 0.5
    visited = [i for c in calls for i in c[0]]
    assert set(visited[:3]) == {0, 2, 4}  # a shuffled cycle: all keyframes before any repeats
    assert torch.equal(loop.keyframes.poses(), poses)
    assert math.isfinite(terms["total"])

    calls.clear()
    monkeypatch.setattr(loop.mapper, "cfg", dataclasses.replace(loop.mapper.cfg, final_iters=0))
    assert final_pass(loop.mapper, loop.keyframes.views(), loop.K, loop.generator) == {} and calls == []


def test_the_first_frame_is_allocated_once(tiny_cube):
    loop = smoke_loop(tiny_cube.intrinsics)
    loop.step(tiny_cube[0])
    assert int(loop.field.grid.voxel_hits.max()) == 1  # one frame: one hit per voxel its depth reached


def test_frames_without_static_depth_are_counted_warned_and_never_mapped(tiny_cube, capsys):
    loop = smoke_loop(tiny_cube.intrinsics)
    for k in range(3):
        loop.step(tiny_cube[k])
    voxels, hits = loop.field.grid.num_voxels, loop.field.grid.voxel_hits.clone()
    blank = dataclasses.replace(tiny_cube[3], depth=torch.zeros_like(tiny_cube[3].depth))
    report = loop.step(blank)
    assert report.track.status is TrackStatus.NO_DEPTH and report.mapping is None
    assert loop.tracker.counts.without_tracking == 1 and loop.field.grid.num_voxels == voxels
    assert torch.equal(loop.field.grid.voxel_hits, hits)  # nothing allocated or counted from it
    err = capsys.readouterr().err
    assert "warning: frame 3" in err and "not tracked, not mapped" in err
    metrics = run_metrics(loop)
    assert metrics["frames_without_tracking"] == 1 and metrics["tracking_lost"] == 0
    assert len(loop) == 4 and not torch.allclose(loop.poses.pose(3), torch.eye(4, dtype=torch.float64))


def test_every_method_runs_in_the_loop(tiny_cube):
    for method in ("odometry", "odometry+field", "field"):
        loop = smoke_loop(tiny_cube.intrinsics, f"tracking.method={method}")
        for k in range(4):
            loop.step(tiny_cube[k])
        gt = [invert_pose(tiny_cube[0].gt_pose) @ tiny_cube[k].gt_pose for k in range(4)]
        err = max(pose_jump(loop.poses.pose(k), gt[k])[0] for k in range(4))
        assert err < 0.03, (method, err)  # smoke settings: 3 field iterations


def test_the_lightning_module_only_adapts_the_loop(tiny_cube, tmp_path):
    system = build_system(smoke_cfg(), tiny_cube.intrinsics, tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log without a Trainer
        for k in range(3):
            system.training_step(tiny_cube[k], k)
    # one frame behind the stream: the frame that arrived last is held, to be tracked while the one before it maps
    assert len(system.loop) == 2 and float(system.held.timestamp) == float(tiny_cube[2].timestamp) and system.field is system.loop.field
    assert not [name for name in vars(system) if name in ("trajectory", "tracked", "db", "timers", "counts")]
    assert isinstance(system.loop.keyframes.view(0), View)


def test_the_first_map_is_deferred_only_where_tracking_does_not_read_it(tiny_cube):
    overrides = ("mapping.first_iters=50", "mapping.first_now=10")
    assert smoke_loop(tiny_cube.intrinsics, *overrides).mapper.cfg.first_now == 10  # odometry: the map is not read
    for method in ("field", "odometry+field"):
        loop = smoke_loop(tiny_cube.intrinsics, *overrides, f"tracking={method}")
        assert loop.mapper.cfg.first_now == 50, method  # frame 1 is tracked against the first map: all of it at once


def test_tracking_the_next_frame_while_mapping_changes_nothing(tiny_cube):
    threads = f"tracking.overlap_threads={torch.get_num_threads()}"  # the same OpenMP partition: bit-identical sums
    assert not smoke_loop(tiny_cube.intrinsics, "tracking.method=odometry+field").overlaps
    assert not smoke_loop(tiny_cube.intrinsics, "mapping.optimize_poses=true").overlaps
    frames = [tiny_cube[k] for k in range(5)]
    torch.manual_seed(0)  # one loop after the other: mapping draws from the global RNG too
    plain = smoke_loop(tiny_cube.intrinsics, threads)
    for frame in frames:
        plain.step(frame)
    torch.manual_seed(0)
    ahead = smoke_loop(tiny_cube.intrinsics, threads)
    assert ahead.overlaps
    for k, frame in enumerate(frames):
        ahead.step(frame, frames[k + 1] if k + 1 < len(frames) else None)
        assert (ahead._ahead is not None) == (k + 1 < len(frames))  # smoke maps every frame: each one overlaps
        # a checkpoint now counts the frames processed, not the one tracked ahead, and holds the objects
        # as they were after this frame (the next one's are observed ahead: they wait for the next step)
        state = ahead.state_dict()
        assert state["tracker"]["counts"]["frames"] == k
        assert all(float(t["taus"][-1]) <= ahead.clock.tau(frame.timestamp) for t in state["objects"]["tracks"].values())
        assert (ahead._ahead is None) or ahead._ahead.objects is not None  # dataset masks: objects observed ahead
    assert torch.equal(ahead.poses.all(), plain.poses.all())
    assert ahead.objects.tracks and ahead.objects.tracks.keys() == plain.objects.tracks.keys()
    for i, track in plain.objects.tracks.items():
        assert ahead.objects.tracks[i].observed_taus() == track.observed_taus()
        assert torch.equal(ahead.objects.tracks[i].poses(), track.poses()) and torch.equal(ahead.objects.tracks[i].box, track.box)
    # mapping alone is not bit-reproducible on CPU (two plain runs differ by ~1e-4: threaded scatter-adds)
    torch.testing.assert_close(ahead.field.grid.embeddings, plain.field.grid.embeddings, atol=1e-3, rtol=0)
    assert ahead.tracker.reference.frame_id == plain.tracker.reference.frame_id


def test_a_step_must_get_the_frame_it_was_told_comes_next(tiny_cube):
    loop = smoke_loop(tiny_cube.intrinsics)
    loop.step(tiny_cube[0], tiny_cube[1])
    with pytest.raises(ValueError, match="as next_frame"):
        loop.step(tiny_cube[2])
