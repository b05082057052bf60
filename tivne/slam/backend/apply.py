"""Applying the back end's corrected keyframe poses: the one place that moves them.

:func:`follow_corrections` takes ``{frame id: corrected c2w}``, hands it to whatever owns the
keyframe poses through the small :class:`KeyframePoses` interface (today
:class:`DatabasePoses` over the keyframe database, the odometry reference and the motion model;
after the loop refactor, the keyframe store's ``update_poses``), then makes the map follow:
voxels are allocated where the moved keyframes' depth now lands and the stale part of the field
is re-fit on them. Frames tracked from a keyframe follow it by construction (the trajectory keeps
their pose relative to it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from tivne.geometry import invert_pose, orthonormalize_pose
from tivne.render.rays import View
from tivne.slam.backend.edges import pose_difference


class KeyframePoses(Protocol):
    """Owner of the keyframe poses: read them, replace some of them."""

    def keyframe_poses(self) -> dict[int, torch.Tensor]: ...

    def update_poses(self, poses: dict[int, torch.Tensor]) -> None: ...


def displacement(old: torch.Tensor, new: torch.Tensor, depth: float = 1.0) -> float:
    """How far (m) a correction moves a surface point ``depth`` metres in front of the camera,
    at most: |Δt| + Δθ·depth (old, new: (4, 4) c2w)."""
    metres, degrees = pose_difference(old, new)
    return metres + math.radians(degrees) * depth


class DatabasePoses:
    """:class:`KeyframePoses` of today's loop: the keyframe views' poses, plus what was tracked
    from them and must move with them -- the odometry reference and the motion model's last poses
    (each moved by the correction of the keyframe it is recorded against in the trajectory)."""

    def __init__(self, views: list[View], tracker: Any, tracked: list[torch.Tensor], trajectory: Any) -> None:
        self.views, self.tracker, self.tracked, self.trajectory = views, tracker, tracked, trajectory

    def keyframe_poses(self) -> dict[int, torch.Tensor]:
        return {v.frame_id: v.pose for v in self.views}

    def update_poses(self, poses: dict[int, torch.Tensor]) -> None:
        deltas: dict[int, torch.Tensor] = {}
        for v in self.views:
            if v.frame_id in poses:
                new = poses[v.frame_id].to(v.pose)
                deltas[v.frame_id] = new.double() @ invert_pose(v.pose.double())
                v.pose = orthonormalize_pose(new)
        ref = getattr(self.tracker, "reference", None)
        if ref is not None:
            ref.pose = self._moved(ref.frame_id, ref.pose, deltas).double()
        n = len(self.trajectory)
        self.tracked[:] = [self._moved(n - len(self.tracked) + i, p, deltas) for i, p in enumerate(self.tracked)]

    def _moved(self, frame_id: int, pose: torch.Tensor, deltas: dict[int, torch.Tensor]) -> torch.Tensor:
        """``pose`` of frame ``frame_id`` moved with its keyframe (unchanged if that did not move)."""
        if frame_id in deltas:
            keyframe = frame_id
        elif 0 <= frame_id < len(self.trajectory.records):
            keyframe = self.trajectory.records[frame_id].keyframe
        else:
            keyframe = None
        if keyframe not in deltas:
            return pose
        return orthonormalize_pose((deltas[keyframe] @ pose.double()).to(pose))


@dataclass(frozen=True)
class Correction:
    """What a pose update did: keyframes (frame ids) moved by more than the re-fit threshold (most
    moved first), the largest displacement (m), and the keyframes re-fit."""

    moved: list[int]
    max_displacement_m: float
    refit: list[int]


def follow_corrections(
    poses: dict[int, torch.Tensor],
    owner: KeyframePoses,
    views: dict[int, View],
    allocate: Callable[[View], None],
    refit: Callable[[list[View]], None],
    min_displacement_m: float,
    refit_window: int,
) -> Correction:
    """Apply corrected keyframe poses and make the map follow them.

    Args:
        poses: {frame id: (4, 4) corrected c2w}; owner: who stores the poses; views: {frame id: keyframe}.
        allocate: allocates voxels where a view's depth lands at its (new) pose.
        refit: runs mapping steps over views at their fixed (new) poses.
        min_displacement_m: a keyframe moved less (:func:`displacement`) is not re-fit.
        refit_window: at most this many of the most moved keyframes are re-fit.
    """
    before = owner.keyframe_poses()
    moves = {i: displacement(before[i], p.to(before[i])) for i, p in poses.items() if i in before}
    owner.update_poses(poses)
    moved = sorted((i for i, d in moves.items() if d > min_displacement_m and i in views), key=lambda i: -moves[i])
    for i in moved:
        allocate(views[i])
    chosen = moved[:refit_window]
    if chosen:
        refit([views[i] for i in chosen])
    return Correction(moved, max(moves.values(), default=0.0), chosen)
