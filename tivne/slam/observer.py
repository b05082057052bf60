"""What the per-frame loop hands to whoever watches a run (a viewer, :mod:`tivne.viewer`): plain
typed records and a small observer protocol, so the loop never imports a viewer (it lives above).

Everything here is cheap to build: tensors are passed as they are (no copies, no host transfer),
and what costs work (a render at the estimated pose, the map's points) is a callable the observer
calls only on the frames it logs, in the loop's thread, between two steps.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

import torch
import trimesh

from tivne.field.networks import TimeVaryingField
from tivne.field.voxels import unpack_keys
from tivne.render.rays import View
from tivne.render.renderer import render_image
from tivne.slam.state import FrameReport
from tivne.slam.tracking import TrackStatus as TrackStatus_
from tivne.slam.tracking.field import frozen

TrackStatus = Literal["first", "tracked", "lost", "untracked"]


@dataclass(frozen=True)
class ObjectState:
    """A moving object at one frame: pose (4, 4) object-to-world (SLAM frame), half_size (3,) metres."""

    pose: torch.Tensor
    half_size: torch.Tensor


@dataclass(frozen=True)
class FrameRecord:
    """One processed frame as the loop saw it.

    index: frame number in the run (0-based); timestamp: seconds on the sequence clock; tau: the
    field's time; pose: (4, 4) estimated c2w (SLAM frame); gt_pose: (4, 4) GT c2w (dataset world
    frame) or None; rgb: (H, W, 3) float 0..1; depth: (H, W) metres (0 = invalid); mask: (H, W)
    bool (True = moving) or None; status: 'first' (defines the world frame), 'tracked', 'lost'
    (tracking failed) or 'untracked' (no usable static depth); is_keyframe; render: returns the
    colour (h, w, 3) and depth (h, w) rendered at ``pose`` with pixel step ``stride`` (None: no
    map yet); objects: id -> :class:`ObjectState` (None: the loop tracks no objects).
    """

    index: int
    timestamp: float
    tau: float
    pose: torch.Tensor
    gt_pose: torch.Tensor | None
    rgb: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor | None
    status: TrackStatus
    is_keyframe: bool
    render: Callable[[int], tuple[torch.Tensor, torch.Tensor]] | None = None
    objects: Mapping[str, ObjectState] | None = None


class RunObserver(Protocol):
    """Receives a run as it happens. Implementations must not raise (a viewer never fails a run)."""

    def on_frame(self, record: FrameRecord) -> None: ...

    def on_map(self, index: int, points: Callable[[], torch.Tensor]) -> None:
        """After the mapping round at frame ``index``; ``points()`` gives (N, 3) map points."""

    def on_mesh(self, timestamp: float, mesh: trimesh.Trimesh) -> None: ...

    def on_finish(self, timestamps: list[float], poses: torch.Tensor) -> None:
        """The final trajectory: (N,) seconds, (N, 4, 4) c2w, keyframe refinements applied."""


class NoObserver:
    """The default: nobody watches."""

    def on_frame(self, record: FrameRecord) -> None:
        pass

    def on_map(self, index: int, points: Callable[[], torch.Tensor]) -> None:
        pass

    def on_mesh(self, timestamp: float, mesh: trimesh.Trimesh) -> None:
        pass

    def on_finish(self, timestamps: list[float], poses: torch.Tensor) -> None:
        pass


def track_status(report: FrameReport) -> TrackStatus:
    """The viewer's status of a frame: 'first' (the world frame), 'tracked' (recovered included),
    'lost' (tracking failed) or 'untracked' (no usable static depth)."""
    if report.index == 0:
        return "first"
    status = report.track.status
    return "lost" if status is TrackStatus_.LOST else "untracked" if status is TrackStatus_.NO_DEPTH else "tracked"


def object_states(report: FrameReport, boxes: Mapping[int, torch.Tensor | None]) -> dict[str, ObjectState] | None:
    """The frame's tracked objects: the pose of each one's box centre and the box's half size
    (``boxes``: object id -> (2, 3) box in object coordinates or None), or None without objects."""
    if not report.objects:
        return None
    out = {}
    for obs in report.objects:
        box = boxes.get(obs.object_id)
        pose = obs.pose.double().clone()
        if box is None:
            half = torch.zeros(3, dtype=torch.float64)
        else:
            box = box.double()
            half = (box[1] - box[0]) / 2
            pose[:3, 3] = pose[:3, 3] + pose[:3, :3] @ ((box[0] + box[1]) / 2)
        out[str(obs.object_id)] = ObjectState(pose, half)
    return out


def frame_record(
    report: FrameReport, gt_pose: torch.Tensor | None, field: TimeVaryingField, K: torch.Tensor, render_cfg,
    boxes: Mapping[int, torch.Tensor | None] | None = None,
) -> FrameRecord:
    """What an observer gets of a processed frame: built from its report (no copies)."""
    v = report.view
    return FrameRecord(report.index, report.timestamp, report.tau, v.pose.detach(), gt_pose, v.colour(), v.depth, v.dynamic,
                       track_status(report), report.keyframe, renderer_at(field, v, K, render_cfg), object_states(report, boxes or {}))


def renderer_at(field: TimeVaryingField, view: View, K: torch.Tensor, cfg) -> Callable[[int], tuple[torch.Tensor, torch.Tensor]]:
    """A callable: stride -> (rgb (h, w, 3), depth (h, w)) rendered from ``field`` at ``view``'s pose and τ."""

    def render(stride: int) -> tuple[torch.Tensor, torch.Tensor]:
        with frozen(field), torch.no_grad():
            return render_image(field, view, K, cfg, stride)

    return render


def map_points(field: TimeVaryingField) -> torch.Tensor:
    """(N, 3) points of the map: the centres of the cells that held static depth (the observed
    surface), or the allocated voxels' centres where none were recorded."""
    grid = field.grid
    if grid.surface_keys.numel():
        return (unpack_keys(grid.surface_keys).float() + 0.5) * grid.surface_cell
    return (grid.voxel_coords().float() + 0.5) * grid.voxel_size
