"""Applying corrected keyframe poses (tivne/slam/backend/apply.py) and the backend config."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from tivne.config import BackendConfig, ConfigError
from tivne.geometry import invert_pose, se3_exp
from tivne.render.rays import View
from tivne.slam.backend import make_backend
from tivne.slam.backend.apply import DatabasePoses, follow_corrections
from tivne.slam.trajectory import Trajectory


def twist(v, w_deg) -> torch.Tensor:
    return se3_exp(torch.tensor([*v, *(math.radians(a) for a in w_deg)], dtype=torch.float64))


def view(frame_id: int, pose: torch.Tensor) -> View:
    return View(frame_id, 0.0, torch.zeros(4, 4, 3), torch.ones(4, 4), None, pose.float())


def test_database_poses_move_views_reference_and_motion_model():
    """Keyframes take their new poses; a reference frame and the motion model's poses move with
    the keyframe they were tracked from."""
    kf0, kf5 = view(0, torch.eye(4, dtype=torch.float64)), view(5, twist((0.1, 0, 0), (0, 5, 0)))
    traj = Trajectory()
    for k in range(8):
        kf = kf0 if k < 5 else kf5
        traj.append(float(k), kf.pose @ twist((0.01 * (k % 5), 0, 0), (0, 0, 0)).float(), kf.frame_id, kf.pose, None)
    frame6, frame7 = traj.poses({0: kf0.pose, 5: kf5.pose})[6:8]
    tracker = SimpleNamespace(reference=SimpleNamespace(frame_id=6, pose=frame6.clone()))
    tracked = [frame6.float(), frame7.float()]
    owner = DatabasePoses([kf0, kf5], tracker, tracked, traj)
    corrected = twist((0.12, 0.01, 0), (0, 6, 0))
    owner.update_poses({5: corrected})
    delta = corrected @ invert_pose(twist((0.1, 0, 0), (0, 5, 0)))
    assert torch.allclose(kf5.pose.double(), corrected, atol=1e-6) and torch.equal(kf0.pose, torch.eye(4))
    assert torch.allclose(tracker.reference.pose, delta @ frame6, atol=1e-6)
    assert torch.allclose(tracked[1].double(), delta @ frame7, atol=1e-5)  # the same list object, mutated
    # frames tracked from kf5 follow it through the trajectory's relative poses
    assert torch.allclose(traj.poses({0: kf0.pose, 5: kf5.pose})[7], delta @ frame7, atol=1e-5)


def test_follow_corrections_allocates_and_refits_the_moved_keyframes():
    views = {i: view(i, twist((0.05 * i, 0, 0), (0, 0, 0))) for i in (0, 5, 10)}
    owner = DatabasePoses(list(views.values()), SimpleNamespace(reference=None), [], Trajectory())
    allocated, refit = [], []
    poses = {0: views[0].pose.double(), 5: views[5].pose.double() @ twist((0.003, 0, 0), (0, 0, 0)),
             10: views[10].pose.double() @ twist((0.0, 0.02, 0), (0, 1, 0))}
    c = follow_corrections(poses, owner, views, lambda v: allocated.append(v.frame_id), lambda vs: refit.append([v.frame_id for v in vs]), 0.01, 4)
    assert c.moved == [10] and allocated == [10] and refit == [[10]]  # 3 mm is below the re-fit threshold
    assert c.max_displacement_m == pytest.approx(0.02 + math.radians(1), abs=1e-3)  # |Δt| + Δθ·1 m


def test_backend_none_builds_nothing_and_graph_without_gtsam_is_one_line(monkeypatch):
    assert make_backend(BackendConfig(), None) is None
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "gtsam" else real(name, *a))
    with pytest.raises(ConfigError, match="backend.method=graph needs gtsam") as info:
        BackendConfig(method="graph")
    assert "\n" not in str(info.value)
