"""objects.track wired into the per-frame loop: tracks per frame, objects/<id>.txt, metrics, resume state."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from data_modules.frame import Intrinsics
from data_modules.tables import read_tum_trajectory
from tivne.slam.results import RunWriter, run_metrics
from tivne.slam.run import TrainSettings, loop_from_config

CONF = Path(__file__).resolve().parents[4] / "conf"


def test_the_loop_tracks_the_object_and_writes_it(tiny_cube, tmp_path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", "output.save_every=0",
                                           "objects.track=true", "objects.min_pixels=50"])
    settings = TrainSettings.from_config(cfg)
    loop = loop_from_config(cfg, tiny_cube.intrinsics)
    reports = [loop.step(tiny_cube[k]) for k in range(4)]
    assert [len(r.objects) for r in reports] == [1, 1, 1, 1]  # the report carries each object's observation
    RunWriter(tmp_path, settings.output, settings.mesh).write_trajectory(loop)
    stamps, poses = read_tum_trajectory(tmp_path / "objects" / "1.txt")
    np.testing.assert_allclose(stamps, tiny_cube.timestamps[:4], atol=1e-6)  # TUM: 6 decimals
    # The object moves in the SLAM world (the first camera's) as it does in the GT world.
    gt = [tiny_cube.object_poses(float(t))["cube"] for t in tiny_cube.timestamps[:4]]
    moved, gt_moved = poses[-1] @ torch.linalg.inv(poses[0]), gt[-1] @ torch.linalg.inv(gt[0])
    w = tiny_cube.camera_pose(0)
    torch.testing.assert_close(w @ moved @ torch.linalg.inv(w), gt_moved, atol=5e-3, rtol=0)
    metrics = run_metrics(loop)
    assert metrics["objects_written"] == 1 and metrics["objects_s_per_frame"] > 0
    assert sorted(loop.state_dict()["objects"]["tracks"]) == [1]


def test_objects_follow_the_masks_of_the_run_unless_told():
    def source(*overrides: str) -> str:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            cfg = compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", "objects.track=true", *overrides])
        return loop_from_config(cfg, Intrinsics(60.0, 60.0, 39.5, 29.5, 80, 60)).objects.source

    assert source("masks=dataset") == "dataset"  # the frames' instance ids
    assert source("masks=geometric") == "geometric"  # segments of the geometric masks: no GT in the run
    assert source("masks=geometric", "objects.source=dataset") == "dataset"


def test_a_dataset_with_motion_masks_but_no_instance_ids_still_gets_its_objects(tiny_cube):
    """objects.source=auto with the dataset's masks: a frame without instance ids (e.g. a dataset
    shipping only binary motion masks) is segmented from its mask instead of losing its objects."""
    import dataclasses

    from tivne.config_optional import ObjectsConfig
    from tivne.slam.objects import ObjectTracker

    tracker = ObjectTracker(ObjectsConfig(track=True, min_pixels=50, border_wait=0), tiny_cube.intrinsics.K())
    frame = tiny_cube[0]
    assert frame.instances is not None
    dynamic = frame.instances > 0
    assert tracker.instances_of(frame, dynamic) is frame.instances
    bare = dataclasses.replace(frame, instances=None)
    assert torch.equal(tracker.instances_of(bare, dynamic), dynamic)
    observed = tracker.observe(bare, tiny_cube.camera_pose(0), 0.0, dynamic)
    assert len(observed) == 1 and observed[0].new_track
