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
last pose (zero motion) with a wider basin (one more pyramid level, twice the iterations). Where the
time since the last frame is not the last step's (frames a recorder dropped, or late), a frame lost
against the one-step constant-velocity prediction is aligned once more from the velocity carried over
the time that passed, and kept where that alignment holds and lands within the jump gate of its own
prediction: a camera that kept moving while frames were missing is not refused as a jump, and the
one-step prediction stays first, since carrying a rocking camera's velocity over a long gap points
it elsewhere. A lost frame keeps the one-step prediction and is never mapped.

The tracker owns no pose: the reference is a frame id, and every pose (the reference's, the motion
model's last two) is read from the run's pose owners through a :class:`PoseLookup`.

Past references are kept (``tracking.stored_references``): when the reference goes stale, the oldest
stored one that sees the new frame's view (:func:`views_seeing`, verified by an alignment) becomes the
reference again, so a camera that returns to a view is tracked against that view's first reference
instead of through the chain of references in between; a new reference is made only where none
fits. Each frame is aligned jointly with its reference and the stored references that see it at the
predicted pose (``tracking.joint_references``).
"""

from __future__ import annotations

import dataclasses
import math
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
from tivne.slam.tracking.overlap import views_seeing
from tivne.slam.tracking.pyramid import PyramidLevel
from tivne.slam.tracking.result import TrackResult, TrackStatus
from tivne.slam.tracking.sensor import Shutter, frame_shutters, moving_shutter, twist_per_second


class PoseLookup(Protocol):
    """The run's poses (c2w, (4, 4)) as their owners hold them now."""

    def pose(self, frame_id: int) -> torch.Tensor: ...

    def recent(self, n: int) -> list[torch.Tensor]: ...

    def recent_times(self, n: int) -> list[float]: ...


@dataclass(frozen=True)
class PyramidSource:
    """What a reference's pyramid is built from: colour (H, W, 3) in [0, 1], depth (H, W) metres,
    dynamic (H, W) bool or None, K (3, 3). A checkpoint stores these (about 5 MB at 640x480, a
    third of the pyramid) and rebuilds the same pyramid."""

    rgb: torch.Tensor
    depth: torch.Tensor
    dynamic: torch.Tensor | None
    K: torch.Tensor

    def pyramid(self, config: OdometryConfig) -> list[PyramidLevel]:
        return frame_pyramid(self.rgb, self.depth, self.K, config, self.dynamic)


FramePyramid = tuple[PyramidSource, list[PyramidLevel]]  # a frame's pyramid and what it is built from


@dataclass
class Reference:
    """A frame the odometry tracks against: its frame id, pyramid (finest first), the pyramid's source and,
    with a rolling shutter, the camera's velocity (6,) when the frame was taken (its rows' motion)."""

    frame_id: int
    pyramid: list[PyramidLevel]
    source: PyramidSource
    velocity: torch.Tensor | None = None


@dataclass
class TrackingCounts:
    """Frames whose pose is not a tracked one, for metrics.json: without_tracking (no usable static
    depth), lost (tracking ran and failed), recovered (the wider retry succeeded); warnings printed;
    seconds / frames / field-tracker iterations spent; reused: switches to a stored reference."""

    without_tracking: int = 0
    lost: int = 0
    recovered: int = 0
    warnings: int = 0
    seconds: float = 0.0
    frames: int = 0
    field_iters: int = 0
    reused: int = 0


def pose_jump(pose: torch.Tensor, predicted: torch.Tensor) -> tuple[float, float]:
    """(metres, degrees) between a tracked and a predicted c2w pose."""
    return pose_difference(predicted, pose)


def velocity_steps(times: list[float], now: float) -> float:
    """How many of the last step's durations lie between the last processed frame and this one:
    (now - t_{k-1}) / (t_{k-1} - t_{k-2}) from ``times`` (seconds, oldest first); 1 without two
    distinct earlier times."""
    if len(times) < 2 or times[-1] <= times[-2]:
        return 1.0
    return (now - times[-1]) / (times[-1] - times[-2])


def reference_to_drop(stored: list[torch.Tensor], max_m: float, max_deg: float) -> int:
    """Which of ``stored`` c2w poses ((4, 4), oldest first; the last is the new current reference) to
    drop when one too many are kept: of the two nearest in pose (metres / max_m + degrees / max_deg)
    the newer, never the oldest (the least drifted) nor the current one; with two, the older."""
    if len(stored) <= 2:
        return 0
    scale_m, scale_deg = max(max_m, 1e-9), max(max_deg, 1e-9)

    def gap(i: int, j: int) -> float:
        metres, degrees = pose_difference(stored[i], stored[j])
        return metres / scale_m + degrees / scale_deg

    return min(((i, j) for j in range(1, len(stored) - 1) for i in range(j)), key=lambda pair: gap(*pair))[1]


class Tracker:
    """Tracks each frame's pose; owns the odometry reference, its counters and its warnings."""

    WARNING_LIMIT = 20
    REUSE_TRIES = 2  # stored references verified by an alignment at a switch, at most

    def __init__(
        self, cfg: TrackingConfig, field_cfg: FieldTrackingConfig, odometry: OdometryConfig, render: RenderConfig, weights: LossWeights,
        readout_s: float = 0.0,
    ) -> None:
        """``readout_s``: the camera's rolling-shutter readout (:class:`Shutter`; 0 = global shutter)."""
        self.cfg, self.field_cfg, self.odometry, self.render, self.weights = cfg, field_cfg, odometry, render, weights
        self.readout_s = readout_s
        wide = dict(levels=odometry.levels + 1, max_iterations=2 * odometry.max_iterations)
        self.recovery = dataclasses.replace(odometry, **wide)
        self.reference: Reference | None = None
        self.stored: list[Reference] = []  # past and current references, oldest first
        self.counts = TrackingCounts()
        self._current: FramePyramid | None = None  # this frame's, until it becomes a reference or the next comes
        self._shutter_dt: float | None = None  # seconds since the last pose, while this frame's shutter is modelled
        self._last_tracked = True  # whether the last frame's pose was measured (TRACKED)

    @property
    def uses_odometry(self) -> bool:
        return self.cfg.method in ("odometry", "odometry+field")

    def track(
        self, index: int, frame: Frame, tau: float, mask: torch.Tensor | None, field: TimeVaryingField,
        poses: PoseLookup, K: torch.Tensor, last_mapped_tau: float, generator: torch.Generator | None = None,
    ) -> TrackResult:
        """The pose of the ``index``-th frame of the stream (``tau`` its field time, ``mask`` its
        motion mask or None). The first frame defines the world frame."""
        self._shutter_dt = None
        if index == 0:
            eye = torch.eye(4, device=frame.depth.device, dtype=frame.depth.dtype)
            return TrackResult(TrackStatus.TRACKED, eye, eye)
        usable = (frame.depth > 0) if mask is None else (frame.depth > 0) & ~mask
        previous = [p.to(frame.depth.dtype) for p in poses.recent(2)]
        if int(usable.sum()) < self.cfg.min_static_pixels:
            self.counts.without_tracking += 1
            self.warn(f"frame {index} (t={float(frame.timestamp):.3f}s): only {int(usable.sum())} static pixels with depth; not tracked, not mapped")
            self._last_tracked = False
            return TrackResult(TrackStatus.NO_DEPTH, previous[-1].clone(), previous[-1].clone())
        start = time.perf_counter()
        query = last_mapped_tau if self.field_cfg.query_time == "last_mapped" else tau
        times = poses.recent_times(2)
        steps = velocity_steps(times, float(frame.timestamp))
        dt = float(frame.timestamp) - times[-1]
        # the velocity is read from the last pose: not from one the odometry did not measure (lost, or the wider retry's)
        self._shutter_dt = dt if self.readout_s > 0 and dt > 0 and self._last_tracked else None
        result = self._track(View(index, query, frame.rgb, frame.depth, mask, previous[-1]), previous, steps, poses, field, K, generator)
        self._last_tracked = result.status is TrackStatus.TRACKED
        if self._shutter_dt is not None and self._last_tracked:
            result = dataclasses.replace(result, velocity=twist_per_second(previous[-1], result.pose, dt))
        self.counts.seconds += time.perf_counter() - start
        self.counts.frames += 1
        self.counts.field_iters += self.field_cfg.iters if self.cfg.reads_map else 0
        self.counts.recovered += int(result.status is TrackStatus.RECOVERED)
        if result.status is TrackStatus.LOST:
            self.counts.lost += 1
            self.warn(f"frame {index} (t={float(frame.timestamp):.3f}s): tracking lost ({result.describe()}); pose from the motion model until the next tracked frame bridges it, not mapped")
        return result

    def _track(
        self, view: View, previous: list[torch.Tensor], steps: float, poses: PoseLookup, field: TimeVaryingField, K: torch.Tensor,
        generator: torch.Generator | None,
    ) -> TrackResult:
        """``steps``: the time since the last frame in durations of the last step (:func:`velocity_steps`)."""
        predicted = predict_pose(previous, self.cfg.motion_model)
        pose, odometry, field_stats, lost, recovered = predicted, None, None, False, False
        if self.uses_odometry and self.reference is not None:
            self._current = self._source_and_pyramid(view, K)
            pose, odometry, recovered = self._odometry(view, previous[-1], predicted, poses, K)
            lost = not odometry.ok
            refused = lost or self._too_far(*pose_jump(pose, predicted))
            timed = predict_pose(previous, self.cfg.motion_model, steps) if refused else predicted
            if not torch.equal(timed, predicted):  # frames dropped or late: again, the velocity over the time that passed
                carried_pose, carried, carried_recovered = self._odometry(view, previous[-1], timed, poses, K)
                if carried.ok and not self._too_far(*pose_jump(carried_pose, timed)):
                    pose, odometry, recovered, predicted, lost = carried_pose, carried, carried_recovered, timed, False
        if not lost and self.cfg.method in ("field", "odometry+field"):
            start = dataclasses.replace(view, pose=pose)
            pose, field_stats = track_frame(field, start, K, self.render, self.weights, self.field_cfg, generator)
            lost = self.cfg.method == "field" and field_stats.inlier_ratio < self.field_cfg.min_inlier_ratio
        jump_m, jump_deg = pose_jump(pose, predicted)
        lost = lost or self._too_far(jump_m, jump_deg)
        status = TrackStatus.LOST if lost else TrackStatus.RECOVERED if recovered else TrackStatus.TRACKED
        final = predicted if lost else orthonormalize_pose(pose)
        return TrackResult(status, final, predicted, odometry, field_stats, jump_m, jump_deg)

    def _too_far(self, metres: float, degrees: float) -> bool:
        """Whether a pose that far from its prediction is a jump (max_jump_m / max_jump_deg)."""
        return metres > self.cfg.max_jump_m or degrees > self.cfg.max_jump_deg

    def _odometry(
        self, view: View, last: torch.Tensor, predicted: torch.Tensor, poses: PoseLookup, K: torch.Tensor
    ) -> tuple[torch.Tensor, OdometryResult, bool]:
        """This frame (its pyramid ``self._current``) aligned to the reference from ``predicted``,
        else from ``last`` with the wider basin: (c2w, the alignment, whether the retry held it)."""
        ref = self.reference
        ref_pose = poses.pose(ref.frame_id).double()
        current = self._current[1]
        to_ref = invert_pose(ref_pose)
        also, others = self._companions(view, ref, ref_pose, predicted, poses, K)
        shutters = self._shutters(to_ref @ last.double(), [ref, *others])
        result = track_pyramids(ref.pyramid, current, to_ref @ predicted.double(), self.odometry, also=also, shutters=shutters)
        recovered = False
        if not result.ok:  # a wider basin, from the last good pose (no motion)
            retry = track_pyramids(ref.pyramid, current, to_ref @ last.double(), self.recovery, shutters=shutters[:2])
            recovered = retry.ok
            result = retry if retry.ok or retry.inlier_ratio > result.inlier_ratio else result
        return (ref_pose @ result.T_ref_cur).to(predicted.dtype), result, recovered

    def _companions(
        self, view: View, ref: Reference, ref_pose: torch.Tensor, predicted: torch.Tensor, poses: PoseLookup, K: torch.Tensor
    ) -> tuple[tuple[tuple[list[PyramidLevel], torch.Tensor], ...], list[Reference]]:
        """Up to ``tracking.joint_references`` stored references besides ``ref`` that see the frame
        at its predicted pose as a reference must (reprojection overlap at least
        reference_min_overlap), from within reuse_max_deg, the most overlapping first, each with its
        T_other_ref (4, 4): aligned jointly with ``ref`` at the finest level, their pixels average out
        each single view's noise, and older views tie the pose to where it was seen before. Also the
        companions themselves, in that order."""
        cfg = self.cfg
        others = [other for other in self.stored if other is not ref]
        if cfg.joint_references <= 0 or not others:
            return (), []
        other_poses = self._poses_of(others, poses)
        seeing = views_seeing(dataclasses.replace(view, pose=predicted), other_poses, K, math.inf, cfg.reuse_max_deg, cfg.reference_min_overlap)
        best = sorted(seeing, key=lambda item: -item[1])[: cfg.joint_references]
        return tuple((others[i].pyramid, invert_pose(other_poses[i]) @ ref_pose) for i, _ in best), [others[i] for i, _ in best]

    def _shutters(self, previous: torch.Tensor, references: list[Reference]) -> tuple[Shutter | None, ...]:
        """This frame's rolling shutter (its velocity read from the estimate and the last pose, ``previous``
        (4, 4) in the reference's frame), then each reference's; () for a global shutter."""
        if self._shutter_dt is None:
            return ()
        current = Shutter(self.readout_s, torch.zeros(6, dtype=torch.float64), previous, self._shutter_dt)
        return (current, *(moving_shutter(self.readout_s, ref.velocity) for ref in references))

    def update_reference(
        self, view: View, K: torch.Tensor, result: TrackResult, is_keyframe: bool, poses: PoseLookup | None = None
    ) -> bool:
        """After a tracked frame: when the reference is gone stale (``tracking.reference``: every
        frame, or when the overlap / inlier ratio with the reference fell below the thresholds, or at
        every mapping keyframe), switch to a stored reference that saw this view (needs ``poses``;
        not with ``reference=frame``) or else make this frame the reference. Returns whether it switched."""
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
        source, pyramid = self._current if self._current is not None else self._source_and_pyramid(view, K)
        known = self._poses_of(self.stored, poses) if poses is not None else None  # the stored references' poses now
        reuse = None
        if known and cfg.reference != "frame":
            candidates = views_seeing(view, known, K, cfg.reuse_max_m, cfg.reuse_max_deg, cfg.reuse_min_overlap)[: self.REUSE_TRIES]
            reuse = next((i for i, _ in candidates if self._aligns(self.stored[i], known[i], view.pose, pyramid, result.velocity)), None)
        if reuse is not None:
            self.reference = self.stored[reuse]
            self.counts.reused += 1
        else:
            self.reference = Reference(view.frame_id, pyramid, source, result.velocity)
            self.stored.append(self.reference)
            if len(self.stored) > cfg.stored_references:
                # this frame is not in the trajectory yet: its pose is the view's; without poses the oldest goes
                drop = 0 if known is None else reference_to_drop([*known, view.pose.double()], cfg.reuse_max_m, cfg.reuse_max_deg)
                self.stored.pop(drop)
        self._current = None
        return True

    def _source_and_pyramid(self, view: View, K: torch.Tensor) -> FramePyramid:
        """This frame's pyramid (with the recovery's extra level) and what it is built from."""
        source = PyramidSource(view.colour(), view.depth, view.dynamic, K)
        return source, source.pyramid(self.recovery)

    @staticmethod
    def _poses_of(references: list[Reference], poses: PoseLookup) -> list[torch.Tensor]:
        """(4, 4) float64 c2w of each reference, as its pose owner holds it now."""
        return [poses.pose(ref.frame_id).double() for ref in references]

    def _aligns(
        self, ref: Reference, ref_pose: torch.Tensor, pose: torch.Tensor, pyramid: list[PyramidLevel], velocity: torch.Tensor | None
    ) -> bool:
        """Whether this frame (``pyramid``, c2w ``pose``) aligns to the stored ``ref`` (c2w
        ``ref_pose``) from their current relative pose: the odometry converges, keeps
        reuse_min_overlap of the frame in view and reference_min_inliers of its pixels (a view seen
        with other blur or exposure, drifted beyond the basin, or already falling behind, is not reused)."""
        shutters = frame_shutters(self.readout_s, velocity, ref.velocity)
        result = track_pyramids(ref.pyramid, pyramid, invert_pose(ref_pose.double()) @ pose.double(), self.odometry, shutters=shutters)
        return result.ok and result.overlap >= self.cfg.reuse_min_overlap and result.inlier_ratio >= self.cfg.reference_min_inliers

    def warn(self, message: str) -> None:
        """A ``warning:`` line on stderr (the first ``WARNING_LIMIT`` of them; metrics.json counts all)."""
        self.counts.warnings += 1
        if self.counts.warnings <= self.WARNING_LIMIT:
            print(f"warning: {message}", file=sys.stderr)
        elif self.counts.warnings == self.WARNING_LIMIT + 1:
            print("warning: more frames without tracking; see tracking_lost / frames_without_tracking in metrics.json", file=sys.stderr)

    def state_dict(self) -> dict:
        """The stored references (frame id and the source of its pyramid, which a load rebuilds),
        which of them is the current one, and the counters."""
        counts = dataclasses.asdict(self.counts)
        if self.reference is None:
            return {"reference": None, "stored": [], "counts": counts}
        # the source's tensors as they are (dataclasses.asdict would deep-copy them first)
        source = [{f.name: getattr(ref.source, f.name) for f in dataclasses.fields(ref.source)} for ref in self.stored]
        saved = [{"frame_id": ref.frame_id, "velocity": ref.velocity} | own for ref, own in zip(self.stored, source)]
        current = next(i for i, ref in enumerate(self.stored) if ref is self.reference)
        return {"reference": current, "stored": saved, "counts": counts}

    def load_state_dict(self, state: dict) -> None:
        self._current = None  # rebuilt by the next frame's tracking
        self.counts = TrackingCounts(**state["counts"])

        def rebuilt(saved: dict) -> Reference:
            source = PyramidSource(saved["rgb"], saved["depth"], saved["dynamic"], saved["K"])
            return Reference(int(saved["frame_id"]), source.pyramid(self.recovery), source, saved.get("velocity"))

        self.stored = [rebuilt(saved) for saved in state["stored"]]
        self.reference = None if state["reference"] is None else self.stored[int(state["reference"])]
