"""objects.track wired into the per-frame loop: tracks per frame, objects/<id>.txt, metrics, resume state."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from data_modules.tables import read_tum_trajectory
from tivne.slam.checkpoint import run_state
from tivne.train import build_system

CONF = Path(__file__).resolve().parents[4] / "conf"


def test_the_loop_tracks_the_object_and_writes_it(tiny_cube, tmp_path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", "output.save_every=0",
                                           "objects.track=true", "objects.min_pixels=50"])
    system = build_system(cfg, tiny_cube.intrinsics, tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log without a Trainer
        for k in range(4):
            system.training_step(tiny_cube[k], k)
    system.write_trajectory()
    stamps, poses = read_tum_trajectory(tmp_path / "objects" / "1.txt")
    np.testing.assert_allclose(stamps, tiny_cube.timestamps[:4], atol=1e-6)  # TUM: 6 decimals
    # The object moves in the SLAM world (the first camera's) as it does in the GT world.
    gt = [tiny_cube.object_poses(float(t))["cube"] for t in tiny_cube.timestamps[:4]]
    moved, gt_moved = poses[-1] @ torch.linalg.inv(poses[0]), gt[-1] @ torch.linalg.inv(gt[0])
    w = tiny_cube.camera_pose(0)
    torch.testing.assert_close(w @ moved @ torch.linalg.inv(w), gt_moved, atol=5e-3, rtol=0)
    metrics = system.run_metrics()
    assert metrics["objects_written"] == 1 and metrics["objects_s_per_frame"] > 0
    assert sorted(run_state(system)["objects"]["tracks"]) == [1]
