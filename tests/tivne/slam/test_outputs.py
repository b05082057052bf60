"""The run directory: paths, the one metrics.json merger, atomic writes (tivne/slam/outputs.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from data_modules.tables import read_tum_trajectory
from tivne.slam.outputs import RunDir, image_panels


def test_merge_metrics_merges_replaces_and_keeps_a_corrupt_file_aside(tmp_path):
    run = RunDir(tmp_path)
    run.merge_metrics({"frames": 3, "ate_rmse_m": None})
    merged = run.merge_metrics({"psnr_db": 20.5, "frames": 4, "nan_value": math.nan, "np": np.float32(1.5)})
    assert merged == json.loads(run.metrics.read_text()) == {"frames": 4, "ate_rmse_m": None, "psnr_db": 20.5, "nan_value": None, "np": 1.5}
    run.metrics.write_text("{broken")
    assert run.merge_metrics({"frames": 1}) == {"frames": 1}
    assert (tmp_path / "metrics.json.corrupt").read_text() == "{broken"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json", "metrics.json.corrupt"]  # no temporaries


def test_merge_metrics_drops_a_stale_reason_once_its_metric_is_computed(tmp_path):
    run = RunDir(tmp_path)
    run.merge_metrics({"ate_rmse_m": None, "ate_reason": "no GT"})
    assert run.merge_metrics({"ate_rmse_m": 0.01})["ate_rmse_m"] == 0.01
    assert "ate_reason" not in run.read_metrics()
    run.merge_metrics({"ssim": None, "ssim_reason": "no checkpoint", "mse": None, "mse_reason": "no checkpoint"})
    merged = run.merge_metrics({"ssim": 0.9})
    assert "ssim_reason" not in merged and merged["mse_reason"] == "no checkpoint"


def test_paths_and_trajectory_round_trip(tmp_path):
    run = RunDir(tmp_path)
    assert run.mesh_path(1.23456).name == "mesh_t1.235.ply" and run.mesh_path(0).parent.name == "meshes"
    assert run.checkpoint == tmp_path / "checkpoints" / "slam.pt"
    poses = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    poses[:, 0, 3] = torch.tensor([0.0, 0.5, 1.0])
    run.write_trajectory([0.0, 0.1, 0.2], poses)
    ts, read = read_tum_trajectory(run.trajectory)
    assert np.allclose(ts, [0.0, 0.1, 0.2]) and torch.allclose(read, poses)


def test_image_panels_put_observed_left_of_rendered(tmp_path):
    rgb_obs, rgb = torch.zeros(4, 5, 3), torch.ones(4, 5, 3)
    depth_obs, depth = torch.full((4, 5), 2.0), torch.full((4, 5), 2.06)
    panels = image_panels(rgb, depth, rgb_obs, depth_obs)
    assert panels["rgb"].shape == (4, 10, 3) and panels["rgb"].dtype == np.uint8
    assert panels["rgb"][0, 0].tolist() == [0, 0, 0] and panels["rgb"][0, 9].tolist() == [255, 255, 255]
    assert panels["depth_error"].shape == (4, 5, 3) and int(panels["depth_error"].max()) == 255  # >= 5 cm = white
    path = RunDir(tmp_path).write_image(RunDir(tmp_path).render_path(7, "rgb"), panels["rgb"])
    assert path.name == "frame00007_rgb.png" and path.stat().st_size > 0


def test_run_dir_rules(tmp_path):
    from tivne.slam.outputs import RunDirError, check_run_dir

    run = RunDir(tmp_path / "run")
    check_run_dir(run, resume=False, overwrite=False)  # a new folder
    run.root.mkdir()
    (run.root / ".hydra").mkdir()
    (run.root / "tb").mkdir()
    check_run_dir(run, resume=False, overwrite=False)  # config and logs alone are not results
    run.merge_metrics({"frames": 3, "complete": False})
    run.checkpoint.parent.mkdir()
    run.checkpoint.write_bytes(b"x")
    with pytest.raises(RunDirError, match=r"already holds results \(metrics.json, checkpoints/\); resume=true .* overwrite=true"):
        check_run_dir(run, resume=False, overwrite=False)
    check_run_dir(run, resume=False, overwrite=True)
    check_run_dir(run, resume=True, overwrite=False)
    saved = {"seed": 0, "tracking": {"iters": 3, "rays": 64}, "resume": False, "hydra": {"run": {"dir": "a"}}}
    check_run_dir(run, True, False, saved, saved | {"resume": True, "hydra": {"run": {"dir": "b"}}})  # where it runs may differ
    with pytest.raises(RunDirError, match=r"different config: tracking.iters \(3 -> 5\), tracking.rays \(64 -> None\)"):
        check_run_dir(run, True, False, saved, saved | {"tracking": {"iters": 5}})
    run.merge_metrics({"complete": True})
    with pytest.raises(RunDirError, match="the run is complete"):
        check_run_dir(run, resume=True, overwrite=False)
    with pytest.raises(RunDirError, match="nothing to resume"):
        check_run_dir(RunDir(tmp_path / "other"), resume=True, overwrite=False)
    (tmp_path / "file").write_text("")
    with pytest.raises(RunDirError, match="run directory is a file"):
        check_run_dir(RunDir(tmp_path / "file"), resume=False, overwrite=False)


def test_clear_results_removes_every_result_and_nothing_else(tmp_path):
    run = RunDir(tmp_path)
    for rel in ("trajectory.txt", "metrics.json", "metrics.json.corrupt", "checkpoints/slam.pt", "meshes/mesh_t0.000.ply",
                "renders/frame00000_rgb.png", "tb/events.out", ".hydra/config.yaml", "train.log"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("old")
    run.clear_results()
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == [".hydra", ".hydra/config.yaml", "train.log"]
    assert run.results() == []


def test_an_interrupted_run_without_a_checkpoint_is_never_sent_in_a_circle(tmp_path):
    """After a second SIGINT (results, no checkpoint): resume=true and a plain start both name
    overwrite=true, and neither suggests the other."""
    from tivne.slam.outputs import RunDirError, check_run_dir

    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    run.merge_metrics({"frames": 3, "complete": False})
    (run.root / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n")
    with pytest.raises(RunDirError) as resumed:
        check_run_dir(run, resume=True, overwrite=False)
    with pytest.raises(RunDirError) as started:
        check_run_dir(run, resume=False, overwrite=False)
    assert "overwrite=true" in str(resumed.value) and "run without resume=true" not in str(resumed.value)
    assert "overwrite=true" in str(started.value) and "resume=true" not in str(started.value)
    check_run_dir(run, resume=False, overwrite=True)  # and that way on is open
