"""Pose bookkeeping of a run: every processed frame's pose, kept relative to a keyframe so that
refining the keyframe moves the frames tracked from it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from data_modules.poses import interpolate_poses
from tivne.geometry import invert_pose, orthonormalize_pose
from tivne.metrics.trajectory import ATEResult, absolute_trajectory_error


@dataclass
class FrameRecord:
    """Where a processed frame's pose lives: relative to the keyframe with frame id ``keyframe``
    ((4, 4) ``relative``), or absolute (``keyframe`` None) once that keyframe's pose is final;
    ``gt_pose`` (4, 4) c2w or None; ``lost``: tracking failed, the pose is the motion model's guess
    until :meth:`Trajectory.bridge_lost` interpolates it."""

    timestamp: float
    keyframe: int | None
    relative: torch.Tensor
    gt_pose: torch.Tensor | None
    lost: bool = False


class Trajectory:
    """The processed frames' poses (c2w, SLAM world frame) and their ground truth where known."""

    def __init__(self) -> None:
        self.records: list[FrameRecord] = []

    def __len__(self) -> int:
        return len(self.records)

    def append(
        self, timestamp: float, pose: torch.Tensor, keyframe: int, keyframe_pose: torch.Tensor, gt_pose: torch.Tensor | None, lost: bool = False
    ) -> None:
        """Record a frame's (4, 4) c2w ``pose`` relative to the keyframe with frame id ``keyframe``
        (at ``keyframe_pose``); ``lost``: the pose is a guess (tracking failed)."""
        rel = orthonormalize_pose(invert_pose(keyframe_pose) @ pose)
        self.records.append(FrameRecord(float(timestamp), int(keyframe), rel.detach(), gt_pose, bool(lost)))

    def bridge_lost(self, keyframe_poses: dict[int, torch.Tensor]) -> int:
        """When the last frame is tracked and the frames just before it were lost: their poses become
        the interpolation in time (SLERP + linear) between the last tracked frame before them and this
        one, in place of the motion model's guess made when they came (which a turn or a jolt, the
        usual reason a frame is lost, makes wrong). Returns how many were bridged; none when no tracked
        frame precedes them."""
        last = len(self.records) - 1
        if last < 1 or self.records[last].lost or not self.records[last - 1].lost:
            return 0
        before = last - 1
        while before >= 0 and self.records[before].lost:
            before -= 1
        if before < 0:
            return 0
        ends = torch.stack([self.pose(before, keyframe_poses), self.pose(last, keyframe_poses)]).cpu()  # interpolate_poses: CPU
        gap = range(before + 1, last)
        times = np.array([self.records[before].timestamp, self.records[last].timestamp])
        bridged, _ = interpolate_poses(times, ends, np.array([self.records[i].timestamp for i in gap]))
        for i, pose in zip(gap, bridged):
            r = self.records[i]
            r.relative = orthonormalize_pose(invert_pose(self._base(r, keyframe_poses).cpu()) @ pose).to(r.relative)
            r.lost = False  # bridged: no longer the guess (the tracker's counters keep that it was lost)
        return len(gap)

    def freeze(self, keyframe: int, keyframe_pose: torch.Tensor) -> None:
        """The keyframe with frame id ``keyframe`` will not move any more (it left the keyframe
        store): its frames' poses become absolute."""
        for r in self.records:
            if r.keyframe == keyframe:
                r.relative, r.keyframe = (keyframe_pose @ r.relative).detach(), None

    def poses(self, keyframe_poses: dict[int, torch.Tensor]) -> torch.Tensor:
        """(N, 4, 4) float64 c2w poses of every frame, with the keyframes' current poses
        (``{frame id: (4, 4) pose}``) applied."""
        if not self.records:
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        return torch.stack(
            [r.relative if r.keyframe is None else keyframe_poses[r.keyframe] @ r.relative for r in self.records]
        ).detach().cpu().double()

    def pose(self, index: int, keyframe_poses: dict[int, torch.Tensor]) -> torch.Tensor:
        """(4, 4) float64 c2w pose of the ``index``-th processed frame (negative: from the end)."""
        r = self.records[index]
        return self._base(r, keyframe_poses) @ r.relative.double()

    @staticmethod
    def _base(record: FrameRecord, keyframe_poses: dict[int, torch.Tensor]) -> torch.Tensor:
        """(4, 4) float64 pose the record's ``relative`` is relative to: its keyframe's, or identity (absolute)."""
        if record.keyframe is None:
            return torch.eye(4, dtype=torch.float64, device=record.relative.device)
        return keyframe_poses[record.keyframe].double()

    def timestamps(self) -> list[float]:
        return [r.timestamp for r in self.records]

    def state_dict(self) -> dict:
        """Every record, stacked (one tensor, not thousands, keeps a checkpoint fast): timestamps
        (N,), keyframe ids (-1 = absolute), relative poses (N, 4, 4) in float64 with each one's
        dtype, GT poses (N, 4, 4) float64 with theirs (None: no GT)."""
        records = self.records
        return {
            "timestamps": [r.timestamp for r in records],
            "keyframes": [-1 if r.keyframe is None else r.keyframe for r in records],
            "relative": stack64([r.relative for r in records]),
            "dtypes": [str(r.relative.dtype).removeprefix("torch.") for r in records],
            "gt": stack64([torch.zeros(4, 4) if r.gt_pose is None else r.gt_pose for r in records]),
            "gt_dtypes": [None if r.gt_pose is None else str(r.gt_pose.dtype).removeprefix("torch.") for r in records],
            "lost": [r.lost for r in records],
        }

    def load_state_dict(self, state: dict) -> None:
        """Records as saved (float32 -> float64 -> float32 is exact, so poses come back bit for bit)."""
        lost = state.get("lost") or [False] * len(state["timestamps"])  # checkpoints before it: none pending
        self.records = [
            FrameRecord(float(t), None if kf < 0 else int(kf), rel.to(getattr(torch, dt)), None if gdt is None else gt.to(getattr(torch, gdt)), bool(ls))
            for t, kf, rel, dt, gt, gdt, ls in zip(
                state["timestamps"], state["keyframes"], state["relative"], state["dtypes"], state["gt"], state["gt_dtypes"], lost
            )
        ]

    def ate(self, keyframe_poses: dict[int, torch.Tensor]) -> ATEResult | None:
        """SE(3)-aligned ATE over the frames that have a GT pose; None with fewer than 3 of them."""
        keep = [i for i, r in enumerate(self.records) if r.gt_pose is not None]
        if len(keep) < 3:
            return None
        est = self.poses(keyframe_poses)[keep]
        gt = torch.stack([self.records[i].gt_pose for i in keep]).detach().cpu().double()
        return absolute_trajectory_error(est.numpy(), gt.numpy(), align="se3")


class PoseBook:
    """Every pose of a run, read from its owners: keyframe poses from the keyframe store (the one
    place they change), every other frame relative to its keyframe in the :class:`Trajectory`.
    What tracking reads (the reference's pose, the motion model's last two) and what is written."""

    def __init__(self, trajectory: Trajectory, keyframe_poses: Callable[[], dict[int, torch.Tensor]]) -> None:
        self.trajectory = trajectory
        self.keyframe_poses = keyframe_poses

    def pose(self, frame_id: int) -> torch.Tensor:
        """(4, 4) float64 c2w of a processed frame (the stream index is the frame id)."""
        return self.trajectory.pose(frame_id, self.keyframe_poses())

    def recent(self, n: int) -> list[torch.Tensor]:
        """The last ``n`` processed frames' (4, 4) float64 c2w poses, oldest first (fewer early on)."""
        kf = self.keyframe_poses()
        count = min(n, len(self.trajectory))
        return [self.trajectory.pose(i, kf) for i in range(-count, 0)]

    def recent_times(self, n: int) -> list[float]:
        """The last ``n`` processed frames' timestamps in seconds, oldest first (fewer early on)."""
        records = self.trajectory.records
        return [r.timestamp for r in records[max(0, len(records) - n):]]

    def all(self) -> torch.Tensor:
        """(N, 4, 4) float64 c2w of every processed frame."""
        return self.trajectory.poses(self.keyframe_poses())


def stack64(poses: list[torch.Tensor]) -> torch.Tensor:
    """(N, 4, 4) float64 on the CPU of N (4, 4) poses (N may be 0)."""
    if not poses:
        return torch.zeros(0, 4, 4, dtype=torch.float64)
    return torch.stack([p.detach().cpu().double() for p in poses])
