"""Per-object trajectory error, Co-Fusion style: the estimate aligned to the ground truth at the
object's first frame, then its translation (ATE) and rotation errors over the observed frames.

The estimated object frame is the tracker's own (e.g. origin at the first observed points' centre),
not the dataset's, and the SLAM world is not the dataset's; both are taken out:

    A(t) = W · T̂(t) · (W · T̂(t0))⁻¹ · T(t0),      E(t) = T(t)⁻¹ · A(t),

with T̂ the estimated object-to-world poses (SLAM world), T the ground truth, W the SLAM-to-world
map (e.g. the first camera's GT pose). A(t) is where the estimated *motion* since t0 puts the GT
object frame, so E is independent of the estimate's choice of object frame; ‖t_E‖ is the error
of the GT object origin (its centre) in metres, angle(R_E) the rotation error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tivne.metrics.trajectory import ArrayLike, _as_np64


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (...) their angles in degrees (atan2: stable near 0 and 180°)."""
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=-1), tr - 1.0))


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:])[..., 0]
    out[..., 3, 3] = 1.0
    return out


@dataclass(frozen=True)
class ObjectTrajectoryError:
    """Errors over ``num_poses`` matched poses: ATE RMSE / max (m) of the GT object origin and
    rotation RMSE / max (degrees), after the first-frame alignment (module docstring)."""

    ate_rmse_m: float
    ate_max_m: float
    rot_rmse_deg: float
    rot_max_deg: float
    num_poses: int

    def as_metrics(self, name: str) -> dict[str, float | int]:
        """metrics.json keys ``object_<name>_ate_m``, ``..._ate_max_m``, ``..._rot_deg``, ``..._rot_max_deg``, ``..._poses``."""
        p = f"object_{name}"
        return {f"{p}_ate_m": self.ate_rmse_m, f"{p}_ate_max_m": self.ate_max_m, f"{p}_rot_deg": self.rot_rmse_deg,
                f"{p}_rot_max_deg": self.rot_max_deg, f"{p}_poses": self.num_poses}


def first_frame_aligned(est: ArrayLike, gt: ArrayLike, world: ArrayLike | None = None) -> np.ndarray:
    """A(t) = W T̂(t) (W T̂(t0))⁻¹ T(t0) (N, 4, 4): the estimated motion applied to the GT pose at t0.

    Args:
        est: (N, 4, 4) estimated object-to-world (SLAM world). gt: (N, 4, 4) GT object-to-world at
            the same times. world: (4, 4) SLAM-to-GT-world map W, or None (identity).
    """
    est, gt = _as_np64(est), _as_np64(gt)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4) or len(est) == 0:
        raise ValueError(f"est and gt must both be (N, 4, 4) with N >= 1, got {est.shape} and {gt.shape}")
    if world is not None:
        est = _as_np64(world)[None] @ est
    return est @ _inv(est[0])[None] @ gt[0][None]


def object_trajectory_error(est: ArrayLike, gt: ArrayLike, world: ArrayLike | None = None) -> ObjectTrajectoryError:
    """Co-Fusion-style object trajectory error of (N, 4, 4) estimated vs GT object-to-world poses at
    the same N times (first = the alignment frame, error 0 there), SLAM-to-world ``world`` (4, 4)."""
    gt = _as_np64(gt)
    E = _inv(gt) @ first_frame_aligned(est, gt, world)
    te = np.linalg.norm(E[:, :3, 3], axis=1)
    re = rotation_angle_deg(E[:, :3, :3])
    return ObjectTrajectoryError(
        ate_rmse_m=float(np.sqrt(np.mean(te**2))), ate_max_m=float(te.max()),
        rot_rmse_deg=float(np.sqrt(np.mean(re**2))), rot_max_deg=float(re.max()), num_poses=int(len(te)),
    )
