"""What tracking hands to the loop: a typed, frozen result per frame (scalars only for logging)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import torch

from tivne.slam.tracking.odometry import OdometryResult


class TrackStatus(Enum):
    """tracked: the pose is a tracked one (the first frame defines the world frame); recovered: the
    first attempt failed and the wider-basin retry succeeded; lost: tracking ran and failed (the pose
    is the motion model's prediction); no_depth: too few static pixels with depth to track on (the
    pose is the last one). Lost and no-depth frames are never mapped."""

    TRACKED = "tracked"
    RECOVERED = "recovered"
    LOST = "lost"
    NO_DEPTH = "no_depth"


@dataclass(frozen=True)
class FieldTrackStats:
    """The field tracker's outcome: best and last loss, share of rays kept by the robust test,
    non-finite steps (the optimisation stopped there)."""

    loss: float
    last_loss: float
    inlier_ratio: float
    nonfinite: int


@dataclass(frozen=True)
class TrackResult:
    """pose (4, 4) c2w of the frame; predicted (4, 4): the motion model's pose; odometry / field: what
    each tracker reported (None where it did not run); jump_m / jump_deg: tracked vs predicted;
    velocity: with a rolling shutter, the camera's body twist (6,) float64 per second while the frame
    was taken, read from the last pose and this one (None where the shutter is not modelled)."""

    status: TrackStatus
    pose: torch.Tensor
    predicted: torch.Tensor
    odometry: OdometryResult | None = None
    field: FieldTrackStats | None = None
    jump_m: float = 0.0
    jump_deg: float = 0.0
    velocity: torch.Tensor | None = None

    @property
    def lost(self) -> bool:
        """No tracked pose (lost or without usable depth): the frame is not mapped."""
        return self.status in (TrackStatus.LOST, TrackStatus.NO_DEPTH)

    def scalars(self) -> dict[str, float]:
        """Log scalars (TensorBoard ``track/<name>``), finite values only."""
        out = {"lost": float(self.lost), "recovered": float(self.status is TrackStatus.RECOVERED),
               "jump_m": self.jump_m, "jump_deg": self.jump_deg}
        odo = self.odometry
        if odo is not None:
            out |= {
                "odo_ok": float(odo.ok), "odo_inlier_ratio": odo.inlier_ratio, "odo_overlap": odo.overlap,
                "odo_rms_photometric": odo.rms_photometric, "odo_rms_geometric_m": odo.rms_geometric,
                "odo_pose_std": odo.pose_std, "odo_iterations": float(sum(odo.iterations)),
            }
        if self.field is not None:
            out |= {"field_loss": self.field.loss, "field_last_loss": self.field.last_loss,
                    "field_inlier_ratio": self.field.inlier_ratio, "field_nonfinite": float(self.field.nonfinite)}
        return {k: float(v) for k, v in out.items() if v is not None and math.isfinite(v)}

    def describe(self) -> str:
        """The signals a warning line names."""
        parts = []
        if self.odometry is not None:
            parts += [f"odo_inlier_ratio {self.odometry.inlier_ratio:.3g}", f"odo_overlap {self.odometry.overlap:.3g}"]
        if self.field is not None:
            parts.append(f"field_inlier_ratio {self.field.inlier_ratio:.3g}")
        parts += [f"jump_m {self.jump_m:.3g}", f"jump_deg {self.jump_deg:.3g}"]
        return ", ".join(parts)
