"""Pose bookkeeping (tivne/slam/trajectory.py): poses relative to keyframes, frozen when a keyframe leaves."""

from __future__ import annotations

import pytest
import torch

from tivne.slam.trajectory import PoseBook, Trajectory


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
    book = PoseBook(traj, lambda: kf)  # what tracking reads: the last poses and their times
    assert book.recent_times(2) == [0.5, 0.6] and book.recent_times(9) == [0.0, 0.1, 0.5, 0.6]
    assert [float(p[0, 3]) for p in book.recent(2)] == pytest.approx([2.0, 2.3])


def turned(x: float, degrees: float) -> torch.Tensor:
    T = shifted(x)
    a = torch.deg2rad(torch.tensor(degrees))
    T[:2, :2] = torch.tensor([[torch.cos(a), -torch.sin(a)], [torch.sin(a), torch.cos(a)]])
    return T


def test_lost_frames_are_bridged_between_their_tracked_neighbours_once_tracking_resumes():
    traj = Trajectory()
    kf = {0: shifted(0.0), 3: turned(0.5, 10.0)}
    traj.append(0.0, turned(0.0, 0.0), 0, kf[0], None)
    traj.append(0.1, turned(0.9, 40.0), 0, kf[0], None, lost=True)  # the motion model's wild guesses
    traj.append(0.2, turned(-0.4, -30.0), 0, kf[0], None, lost=True)
    assert traj.bridge_lost(kf) == 0  # nothing tracked after them yet
    traj.append(0.3, turned(0.6, 30.0), 3, kf[3], None)
    assert traj.bridge_lost(kf) == 2
    poses = traj.poses(kf)
    for i, s in ((1, 1 / 3), (2, 2 / 3)):  # SLERP + linear in time between frames 0 and 3
        assert torch.allclose(poses[i], turned(0.6 * s, 30.0 * s).double(), atol=1e-6)
    assert traj.bridge_lost(kf) == 0  # done once
    kf[0] = shifted(0.1)  # they stay relative to their own keyframe
    assert torch.allclose(traj.poses(kf)[1, 0, 3], torch.tensor(0.3, dtype=torch.float64), atol=1e-6)
    restored = Trajectory()
    restored.load_state_dict(traj.state_dict())
    assert [r.lost for r in restored.records] == [r.lost for r in traj.records]


def test_lost_frames_without_a_tracked_frame_before_them_keep_their_guess():
    traj = Trajectory()
    kf = {0: shifted(0.0)}
    traj.append(0.0, shifted(0.3), 0, kf[0], None, lost=True)
    traj.append(0.1, shifted(0.5), 0, kf[0], None)
    assert traj.bridge_lost(kf) == 0 and torch.allclose(traj.poses(kf)[0, 0, 3], torch.tensor(0.3, dtype=torch.float64))
