"""Applying the back end's corrected keyframe poses: the one place that moves them.

:func:`follow_corrections` takes ``{frame id: corrected c2w}``, hands it to whatever owns the
keyframe poses through the small :class:`KeyframePoses` interface (the keyframe store: the one
owner of keyframe poses; the odometry reference and the motion model read theirs from the
trajectory, so they follow without being told), then makes the map follow:
voxels are allocated where the moved keyframes' depth now lands and the stale part of the field
is re-fit on them. Frames tracked from a keyframe follow it by construction (the trajectory keeps
their pose relative to it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch

from tivne.geometry import orthonormalize_pose, pose_difference
from tivne.render.rays import View


class KeyframePoses(Protocol):
    """Owner of the keyframe poses: read them, replace some of them."""

    def pose_map(self) -> dict[int, torch.Tensor]: ...

    def update_poses(self, poses: dict[int, torch.Tensor]) -> None: ...


def displacement(old: torch.Tensor, new: torch.Tensor, depth: float = 1.0) -> float:
    """How far (m) a correction moves a surface point ``depth`` metres in front of the camera,
    at most: |Δt| + Δθ·depth (old, new: (4, 4) c2w)."""
    metres, degrees = pose_difference(old, new)
    return metres + math.radians(degrees) * depth


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
    view_of: Callable[[int], View],
    allocate: Callable[[View], None],
    refit: Callable[[list[View]], None],
    min_displacement_m: float,
    refit_window: int,
) -> Correction:
    """Apply corrected keyframe poses and make the map follow them.

    Args:
        poses: {frame id: (4, 4) corrected c2w}; owner: who stores the poses; view_of: a keyframe's
        view at its current pose (read after the update).
        allocate: allocates voxels where a view's depth lands at its (new) pose.
        refit: runs mapping steps over views at their fixed (new) poses.
        min_displacement_m: a keyframe moved less (:func:`displacement`) is not re-fit.
        refit_window: at most this many of the most moved keyframes are re-fit.
    """
    before = owner.pose_map()
    moves = {i: displacement(before[i], p.to(before[i])) for i, p in poses.items() if i in before}
    owner.update_poses({i: orthonormalize_pose(p.to(before[i])) for i, p in poses.items() if i in before})
    moved = sorted((i for i, d in moves.items() if d > min_displacement_m), key=lambda i: -moves[i])
    for i in moved:
        allocate(view_of(i))
    chosen = moved[:refit_window]
    if chosen:
        refit([view_of(i) for i in chosen])
    return Correction(moved, max(moves.values(), default=0.0), chosen)
