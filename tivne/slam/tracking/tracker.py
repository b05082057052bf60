"""The tracking front end: each frame's camera pose, by dense RGB-D odometry against a reference
frame, optionally refined against the field, with its own checks, counters and warning lines.

``tracking.method``:
    * ``field``: the paper's tracker alone (:func:`tivne.slam.tracking.field.track_frame`) from the
      motion model's prediction;
    * ``odometry``: coarse-to-fine RGB-D odometry (:mod:`tivne.slam.tracking.odometry`) against the
      reference frame, from the motion model's prediction;
    * ``odometry+field``: the odometry's pose refined by the field tracker (``field_tracking.iters`` steps).

Before tracking, a frame with fewer than ``tracking.min_static_pixels`` static pixels with depth is
not tracked (:attr:`TrackStatus.NO_DEPTH`). Loss (:attr:`TrackStatus.LOST`): the odometry (and its
recovery) reports failure, or, for the field tracker alone, its inlier ratio falls below
``field_tracking.min_inlier_ratio``, or the pose jumps further from the motion model's prediction
than ``tracking.max_jump_m`` / ``max_jump_deg``. Recovery re-tracks against the reference from the
last pose (zero motion) with a wider basin (one more pyramid level, twice the iterations). A lost
frame keeps the predicted pose and is never mapped.

The tracker owns no pose: the reference is a frame id, and every pose (the reference's, the motion
model's last two) is read from the run's pose owners through a :class:`PoseLookup`.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass
from typing import Protocol

import torch

from data_modules.frame import Frame
from tivne.config import FieldTrackingConfig, LossWeights, OdometryConfig, RenderConfig, TrackingConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import invert_pose, orthonormalize_pose, pose_difference
from tivne.render.rays import View
from tivne.slam.tracking.field import predict_pose, track_frame
from tivne.slam.tracking.odometry import OdometryResult, frame_pyramid, track_pyramids
from tivne.slam.tracking.pyramid import PyramidLevel
from tivne.slam.tracking.result import TrackResult, TrackStatus


class PoseLookup(Protocol):
    """The run's poses (c2w, (4, 4)) as their owners hold them now."""

    def pose(self, frame_id: int) -> torch.Tensor: ...

    def recent(self, n: int) -> list[torch.Tensor]: ...


@dataclass
class Reference:
    """The frame the odometry tracks against: its frame id and pyramid (finest first)."""

    frame_id: int
    pyramid: list[PyramidLevel]


@dataclass
class TrackingCounts:
    """Frames whose pose is not a tracked one, for metrics.json: without_tracking (no usable static
    depth), lost (tracking ran and failed), recovered (the wider retry succeeded); warnings printed;
    seconds / frames / field-tracker iterations spent."""

    without_tracking: int = 0
    lost: int = 0
    recovered: int = 0
    warnings: int = 0
    seconds: float = 0.0
    frames: int = 0
    field_iters: int = 0


def pose_jump(pose: torch.Tensor, predicted: torch.Tensor) -> tuple[float, float]:
    """(metres, degrees) between a tracked and a predicted c2w pose."""
    return pose_difference(predicted, pose)


class Tracker:
    """Tracks each frame's pose; owns the odometry reference, its counters and its warnings."""

    WARNING_LIMIT = 20

    def __init__(
        self, cfg: TrackingConfig, field_cfg: FieldTrackingConfig, odometry: OdometryConfig, render: RenderConfig, weights: LossWeights
    ) -> None:
        self.cfg, self.field_cfg, self.odometry, self.render, self.weights = cfg, field_cfg, odometry, render, weights
        wide = dict(levels=odometry.levels + 1, max_iterations=2 * odometry.max_iterations)
        self.recovery = dataclasses.replace(odometry, **wide)
        self.reference: Reference | None = None
        self.counts = TrackingCounts()
        self._current: list[PyramidLevel] | None = None

    @property
    def uses_odometry(self) -> bool:
        return self.cfg.method in ("odometry", "odometry+field")

    def track(
        self, index: int, frame: Frame, tau: float, mask: torch.Tensor | None, field: TimeVaryingField,
        poses: PoseLookup, K: torch.Tensor, last_mapped_tau: float, generator: torch.Generator | None = None,
    ) -> TrackResult:
        """The pose of the ``index``-th frame of the stream (``tau`` its field time, ``mask`` its
        motion mask or None). The first frame defines the world frame."""
        if index == 0:
            eye = torch.eye(4, device=frame.depth.device, dtype=frame.depth.dtype)
            return TrackResult(TrackStatus.TRACKED, eye, eye)
        usable = (frame.depth > 0) if mask is None else (frame.depth > 0) & ~mask
        previous = [p.to(frame.depth.dtype) for p in poses.recent(2)]
        if int(usable.sum()) < self.cfg.min_static_pixels:
            self.counts.without_tracking += 1
            self.warn(f"frame {index} (t={float(frame.timestamp):.3f}s): only {int(usable.sum())} static pixels with depth; not tracked, not mapped")
            return TrackResult(TrackStatus.NO_DEPTH, previous[-1].clone(), previous[-1].clone())
        start = time.perf_counter()
        query = last_mapped_tau if self.field_cfg.query_time == "last_mapped" else tau
        result = self._track(View(index, query, frame.rgb, frame.depth, mask, previous[-1]), previous, poses, field, K, generator)
        self.counts.seconds += time.perf_counter() - start
        self.counts.frames += 1
        self.counts.field_iters += self.field_cfg.iters if self.cfg.reads_map else 0
        self.counts.recovered += int(result.status is TrackStatus.RECOVERED)
        if result.status is TrackStatus.LOST:
            self.counts.lost += 1
            self.warn(f"frame {index} (t={float(frame.timestamp):.3f}s): tracking lost ({result.describe()}); pose from the motion model, not mapped")
        return result

    def _track(
        self, view: View, previous: list[torch.Tensor], poses: PoseLookup, field: TimeVaryingField, K: torch.Tensor,
        generator: torch.Generator | None,
    ) -> TrackResult:
        predicted = predict_pose(previous, self.cfg.motion_model)
        pose, odometry, field_stats, lost, recovered = predicted, None, None, False, False
        if self.uses_odometry and self.reference is not None:
            pose, odometry, recovered = self._odometry(view, previous[-1], predicted, poses, K)
            lost = not odometry.ok
        if not lost and self.cfg.method in ("field", "odometry+field"):
            start = dataclasses.replace(view, pose=pose)
            pose, field_stats = track_frame(field, start, K, self.render, self.weights, self.field_cfg, generator)
            lost = self.cfg.method == "field" and field_stats.inlier_ratio < self.field_cfg.min_inlier_ratio
        jump_m, jump_deg = pose_jump(pose, predicted)
        lost = lost or jump_m > self.cfg.max_jump_m or jump_deg > self.cfg.max_jump_deg
        status = TrackStatus.LOST if lost else TrackStatus.RECOVERED if recovered else TrackStatus.TRACKED
        final = predicted if lost else orthonormalize_pose(pose)
        return TrackResult(status, final, predicted, odometry, field_stats, jump_m, jump_deg)

    def _odometry(
        self, view: View, last: torch.Tensor, predicted: torch.Tensor, poses: PoseLookup, K: torch.Tensor
    ) -> tuple[torch.Tensor, OdometryResult, bool]:
        ref = self.reference
        ref_pose = poses.pose(ref.frame_id).double()
        self._current = frame_pyramid(view.colour(), view.depth, K, self.recovery, view.dynamic)
        to_ref = invert_pose(ref_pose)
        result = track_pyramids(ref.pyramid, self._current, to_ref @ predicted.double(), self.odometry)
        recovered = False
        if not result.ok:  # a wider basin, from the last good pose (no motion)
            retry = track_pyramids(ref.pyramid, self._current, to_ref @ last.double(), self.recovery)
            recovered = retry.ok
            result = retry if retry.ok or retry.inlier_ratio > result.inlier_ratio else result
        return (ref_pose @ result.T_ref_cur).to(predicted.dtype), result, recovered

    def update_reference(self, view: View, K: torch.Tensor, result: TrackResult, is_keyframe: bool) -> bool:
        """After a tracked frame: make it the odometry reference when the reference is gone stale
        (``tracking.reference``: every frame, or when the overlap / inlier ratio with the reference
        fell below the thresholds, or at every mapping keyframe). Returns whether it switched."""
        if not self.uses_odometry:
            return False
        cfg, odo = self.cfg, result.odometry
        stale = (
            self.reference is None
            or cfg.reference == "frame"
            or (cfg.reference == "keyframe" and is_keyframe)
            or (odo is not None and odo.overlap < cfg.reference_min_overlap)
            or (odo is not None and odo.inlier_ratio < cfg.reference_min_inliers)
        )
        if not stale:
            return False
        pyramid = self._current if self._current is not None else frame_pyramid(view.colour(), view.depth, K, self.recovery, view.dynamic)
        self.reference = Reference(view.frame_id, pyramid)
        self._current = None
        return True

    def warn(self, message: str) -> None:
        """A ``warning:`` line on stderr (the first ``WARNING_LIMIT`` of them; metrics.json counts all)."""
        self.counts.warnings += 1
        if self.counts.warnings <= self.WARNING_LIMIT:
            print(f"warning: {message}", file=sys.stderr)
        elif self.counts.warnings == self.WARNING_LIMIT + 1:
            print("warning: more frames without tracking; see tracking_lost / frames_without_tracking in metrics.json", file=sys.stderr)

    def state_dict(self) -> dict:
        """The odometry reference (frame id, its pyramid as built from the full-precision frame) and the counters."""
        ref = self.reference
        counts = dataclasses.asdict(self.counts)
        if ref is None:
            return {"reference": None, "counts": counts}
        levels = [{f.name: getattr(level, f.name) for f in dataclasses.fields(level)} for level in ref.pyramid]
        return {"reference": {"frame_id": ref.frame_id, "pyramid": levels}, "counts": counts}

    def load_state_dict(self, state: dict) -> None:
        ref = state.get("reference")
        self._current = None  # rebuilt by the next frame's tracking
        self.counts = TrackingCounts(**state["counts"])
        self.reference = None if ref is None else Reference(int(ref["frame_id"]), [PyramidLevel(**level) for level in ref["pyramid"]])
