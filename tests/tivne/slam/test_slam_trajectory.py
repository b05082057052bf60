"""Pose bookkeeping (tivne/slam/trajectory.py): poses relative to keyframes, frozen when a keyframe leaves."""

from __future__ import annotations

import torch

from tivne.slam.trajectory import Trajectory


def shifted(x: float) -> torch.Tensor:
    T = torch.eye(4)
    T[0, 3] = x
    return T


def test_frames_follow_their_keyframe_until_it_is_frozen():
    traj = Trajectory()
    kf = {0: shifted(0.0), 5: shifted(1.0)}
    traj.append(0.0, shifted(0.0), 0, kf[0], None)
    traj.append(0.1, shifted(0.2), 0, kf[0], None)
    traj.append(0.5, shifted(1.0), 5, kf[5], None)
    traj.append(0.6, shifted(1.3), 5, kf[5], None)
    assert torch.allclose(traj.poses(kf)[:, 0, 3], torch.tensor([0.0, 0.2, 1.0, 1.3], dtype=torch.float64))
    kf[5] = shifted(2.0)  # mapping moved keyframe 5: its frames move with it
    assert torch.allclose(traj.poses(kf)[:, 0, 3], torch.tensor([0.0, 0.2, 2.0, 2.3], dtype=torch.float64))
    traj.freeze(5, kf.pop(5))  # it left the store: its frames keep their poses without it
    assert torch.allclose(traj.poses(kf)[:, 0, 3], torch.tensor([0.0, 0.2, 2.0, 2.3], dtype=torch.float64))
    assert traj.ate(kf) is None and traj.timestamps() == [0.0, 0.1, 0.5, 0.6]
