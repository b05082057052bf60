"""Applying corrected keyframe poses (tivne/slam/backend/apply.py) and the backend config."""

from __future__ import annotations

import math

import pytest
import torch

from tivne.config import BackendConfig, ConfigError, KeyframeConfig
from tivne.geometry import invert_pose, se3_exp
from tivne.render.rays import View
from tivne.slam.backend import make_backend
from tivne.slam.backend.apply import follow_corrections
from tivne.slam.keyframes import KeyframeStore
from tivne.slam.trajectory import PoseBook, Trajectory


def twist(v, w_deg) -> torch.Tensor:
    return se3_exp(torch.tensor([*v, *(math.radians(a) for a in w_deg)], dtype=torch.float64))


def view(frame_id: int, pose: torch.Tensor) -> View:
    return View(frame_id, 0.0, torch.zeros(4, 4, 3), torch.ones(4, 4), None, pose.float())


def store_with(views: list[View]) -> KeyframeStore:
    store = KeyframeStore(KeyframeConfig(every=1))
    for v in views:
        store.add(v)
    return store


def test_one_update_moves_keyframes_and_everything_tracked_from_them():
    """The keyframe store is the one owner: after update_poses, the frames tracked from a keyframe
    (the odometry reference's pose, the motion model's last poses) follow it through the trajectory."""
    kf0, kf5 = view(0, torch.eye(4, dtype=torch.float64)), view(5, twist((0.1, 0, 0), (0, 5, 0)))
    store = store_with([kf0, kf5])
    traj = Trajectory()
    for k in range(8):
        kf = kf0 if k < 5 else kf5
        traj.append(float(k), kf.pose @ twist((0.01 * (k % 5), 0, 0), (0, 0, 0)).float(), kf.frame_id, kf.pose, None)
    book = PoseBook(traj, store.pose_map)
    frame6, frame7 = book.pose(6), book.pose(7)
    corrected = twist((0.12, 0.01, 0), (0, 6, 0))
    store.update_poses({5: corrected})
    delta = corrected @ invert_pose(twist((0.1, 0, 0), (0, 5, 0)))
    assert torch.allclose(store.pose(5).double(), corrected, atol=1e-6) and torch.equal(store.pose(0), torch.eye(4))
    assert torch.allclose(book.pose(6), delta @ frame6, atol=1e-5)  # a reference frame's pose, as the tracker reads it
    assert torch.allclose(book.recent(2)[1], delta @ frame7, atol=1e-5)  # the motion model's last pose


def test_follow_corrections_allocates_and_refits_the_moved_keyframes():
    views = [view(i, twist((0.05 * i, 0, 0), (0, 0, 0))) for i in (0, 5, 10)]
    store = store_with(views)
    allocated, refit = [], []
    poses = {0: views[0].pose.double(), 5: views[1].pose.double() @ twist((0.003, 0, 0), (0, 0, 0)),
             10: views[2].pose.double() @ twist((0.0, 0.02, 0), (0, 1, 0))}
    ids = store.frame_ids()
    c = follow_corrections(poses, store, lambda i: store.view(ids.index(i)), lambda v: allocated.append((v.frame_id, v.pose.clone())),
                           lambda vs: refit.append([v.frame_id for v in vs]), 0.01, 4)
    assert c.moved == [10] and [i for i, _ in allocated] == [10] and refit == [[10]]  # 3 mm is below the re-fit threshold
    assert torch.allclose(allocated[0][1].double(), poses[10], atol=1e-6)  # allocated at the corrected pose
    assert c.max_displacement_m == pytest.approx(0.02 + math.radians(1), abs=1e-3)  # |Δt| + Δθ·1 m


def test_backend_none_builds_nothing_and_graph_without_gtsam_is_one_line(monkeypatch):
    assert make_backend(BackendConfig(), None) is None
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "gtsam" else real(name, *a))
    with pytest.raises(ConfigError, match="backend.method=graph needs gtsam") as info:
        BackendConfig(method="graph")
    assert "\n" not in str(info.value)
