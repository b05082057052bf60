"""The tracking front end: dense RGB-D odometry against a reference keyframe, optionally refined
against the field, with tracking-loss detection and recovery.

``tracking.method``:
    * ``field``: the paper's tracker alone (:func:`tivne.slam.tracking.track_frame`) from the motion
      model's prediction;
    * ``odometry``: coarse-to-fine RGB-D odometry (:mod:`tivne.slam.odometry`) against the reference
      keyframe, from the motion model's prediction;
    * ``odometry+field``: the odometry's pose refined by the field tracker (``tracking.iters`` steps).

Loss: a frame is *lost* when the odometry (and its recovery) reports failure, or, for the field
tracker alone, when its inlier ratio falls below ``tracking.min_inlier_ratio``, or when the pose
jumps further from the motion model's prediction than ``tracking.max_jump_m`` / ``max_jump_deg``.
Recovery re-tracks against the reference from the last good pose (zero motion) with a wider basin
(one more pyramid level, twice the iterations). A lost frame keeps the predicted pose, is reported,
and is never mapped (the caller checks :attr:`TrackResult.lost`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from tivne.config import LossWeights, OdometryConfig, RenderConfig, TrackingConfig
from tivne.field.networks import TimeVaryingField
from tivne.geometry import invert_pose, orthonormalize_pose
from tivne.render.rays import View
from tivne.slam.odometry import OdometryResult, frame_pyramid, track_pyramids
from tivne.slam.pyramid import PyramidLevel
from tivne.slam.tracking import predict_pose, track_frame


@dataclass
class Reference:
    """The frame the odometry tracks against: its pyramid (finest first) and c2w pose (4, 4) float64."""

    frame_id: int
    pyramid: list[PyramidLevel]
    pose: torch.Tensor


@dataclass
class TrackResult:
    """pose (4, 4) c2w; lost: tracking failed (the pose is the motion model's prediction);
    recovered: the first attempt failed and recovery succeeded; stats: scalars for the logs."""

    pose: torch.Tensor
    lost: bool
    recovered: bool
    stats: dict[str, float]


def rotation_deg(T: torch.Tensor) -> float:
    """Rotation angle (degrees) of a (4, 4) rigid transform."""
    cos = ((T[:3, :3].trace() - 1) / 2).clamp(-1, 1)
    return math.degrees(float(torch.arccos(cos)))


def pose_jump(pose: torch.Tensor, predicted: torch.Tensor) -> tuple[float, float]:
    """(metres, degrees) between a tracked and a predicted c2w pose."""
    D = invert_pose(predicted.double()) @ pose.double()
    return float(D[:3, 3].norm()), rotation_deg(D)


class Tracker:
    """Tracks each frame's pose; owns the odometry reference keyframe."""

    def __init__(self, cfg: TrackingConfig, odometry: OdometryConfig, render: RenderConfig, weights: LossWeights) -> None:
        self.cfg, self.odometry, self.render, self.weights = cfg, odometry, render, weights
        wide = dict(levels=odometry.levels + 1, max_iterations=2 * odometry.max_iterations)
        self.recovery = dataclasses.replace(odometry, **wide)
        self.reference: Reference | None = None
        self._current: list[PyramidLevel] | None = None

    @property
    def uses_odometry(self) -> bool:
        return self.cfg.method in ("odometry", "odometry+field")

    def track(
        self, field: TimeVaryingField, view: View, previous: list[torch.Tensor], K: torch.Tensor, generator: torch.Generator | None
    ) -> TrackResult:
        """The pose of ``view`` (its ``pose`` is ignored; ``previous`` are the last tracked c2w poses,
        at least one). ``view.tau`` is the time the field is queried at."""
        predicted = predict_pose(previous, self.cfg.motion_model)
        stats: dict[str, float] = {}
        pose, lost, recovered = predicted, False, False
        if self.uses_odometry and self.reference is not None:
            pose, lost, recovered, stats = self._odometry(view, previous[-1], predicted, K)
        if not lost and self.cfg.method in ("field", "odometry+field"):
            start = View(view.frame_id, view.tau, view.rgb, view.depth, view.dynamic, pose)
            pose, field_stats = track_frame(field, start, K, self.render, self.weights, self.cfg, generator)
            stats |= {f"field_{k}": v for k, v in field_stats.items()}
            lost = self.cfg.method == "field" and field_stats["inlier_ratio"] < self.cfg.min_inlier_ratio
        jump_m, jump_deg = pose_jump(pose, predicted)
        stats |= {"jump_m": jump_m, "jump_deg": jump_deg}
        if jump_m > self.cfg.max_jump_m or jump_deg > self.cfg.max_jump_deg:
            lost = True
        recovered = recovered and not lost
        stats |= {"lost": float(lost), "recovered": float(recovered)}
        return TrackResult(predicted if lost else orthonormalize_pose(pose), lost, recovered, stats)

    def _odometry(
        self, view: View, last: torch.Tensor, predicted: torch.Tensor, K: torch.Tensor
    ) -> tuple[torch.Tensor, bool, bool, dict[str, float]]:
        ref = self.reference
        self._current = frame_pyramid(view.colour(), view.depth, K, self.recovery, view.dynamic)
        to_ref = invert_pose(ref.pose)
        result = track_pyramids(ref.pyramid, self._current, to_ref @ predicted.double(), self.odometry)
        recovered = False
        if not result.ok:  # a wider basin, from the last good pose (no motion)
            retry = track_pyramids(ref.pyramid, self._current, to_ref @ last.double(), self.recovery)
            recovered = retry.ok
            result = retry if retry.ok or retry.inlier_ratio > result.inlier_ratio else result
        stats = odometry_stats(result)
        pose = (ref.pose @ result.T_ref_cur).to(predicted.dtype)
        return pose, not result.ok, recovered, stats

    def update_reference(self, view: View, K: torch.Tensor, stats: dict[str, float], is_keyframe: bool) -> bool:
        """After a tracked frame: make it the odometry reference when the reference is gone stale
        (``tracking.reference``: every frame, or when the overlap / inlier ratio with the reference
        fell below the thresholds, or at every mapping keyframe). Returns whether it switched."""
        if not self.uses_odometry:
            return False
        cfg = self.cfg
        stale = (
            self.reference is None
            or cfg.reference == "frame"
            or (cfg.reference == "keyframe" and is_keyframe)
            or stats.get("odo_overlap", 1.0) < cfg.reference_min_overlap
            or stats.get("odo_inlier_ratio", 1.0) < cfg.reference_min_inliers
        )
        if not stale:
            return False
        pyramid = self._current if self._current is not None else frame_pyramid(view.colour(), view.depth, K, self.recovery, view.dynamic)
        self.reference = Reference(view.frame_id, pyramid, view.pose.detach().double())
        self._current = None
        return True


    def state_dict(self) -> dict:
        """The odometry reference (frame id, pose, its pyramid as built from the full-precision
        frame), or None before the first frame."""
        ref = self.reference
        if ref is None:
            return {"reference": None}
        levels = [{f.name: getattr(level, f.name) for f in dataclasses.fields(level)} for level in ref.pyramid]
        return {"reference": {"frame_id": ref.frame_id, "pose": ref.pose, "pyramid": levels}}

    def load_state_dict(self, state: dict) -> None:
        ref = state.get("reference")
        self._current = None  # rebuilt by the next frame's tracking
        if ref is None:
            self.reference = None
            return
        self.reference = Reference(int(ref["frame_id"]), [PyramidLevel(**level) for level in ref["pyramid"]], ref["pose"])


def odometry_stats(result: OdometryResult) -> dict[str, float]:
    """The odometry's quality signals as log scalars."""
    return {
        "odo_ok": float(result.ok),
        "odo_inlier_ratio": result.inlier_ratio,
        "odo_overlap": result.overlap,
        "odo_rms_photometric": result.rms_photometric,
        "odo_rms_geometric_m": result.rms_geometric,
        "odo_pose_std": result.pose_std,
        "odo_iterations": float(sum(result.iterations)),
    }
