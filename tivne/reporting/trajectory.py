"""A run's trajectory against ground truth, per frame, for the report's plots (numbers come from
:mod:`tivne.evaluation`: the same association and SE(3) alignment as the ATE in metrics.json)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tivne.evaluation import trajectory_metrics


@dataclass(frozen=True)
class TrajectoryErrors:
    """The estimate aligned to GT (SE(3), as the ATE), at the N associated frames.

    times: (N,) seconds since the run's first frame; estimated, reference: (N, 3) positions in the
    GT world frame; translation_m: (N,) position error; rotation_deg: (N,) angle between the
    estimated orientation and GT's after the one constant rotation that aligns them best
    (:func:`orientation_alignment`); reference_poses: (N, 4, 4) GT c2w.
    """

    times: np.ndarray
    estimated: np.ndarray
    reference: np.ndarray
    translation_m: np.ndarray
    rotation_deg: np.ndarray
    reference_poses: np.ndarray


def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations -> (N,) angles in degrees."""
    cos = (np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def orientation_alignment(reference: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    """(3, 3) rotation A minimising Σ ‖R_ref,i − A R_est,i‖² over (N, 3, 3) orientations.

    Not the ATE's alignment: that one is fitted to positions, and along a nearly straight path it
    leaves the roll about the path free, which would show as a constant rotation error.
    """
    u, _, vt = np.linalg.svd((reference @ np.swapaxes(estimated, 1, 2)).sum(axis=0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def trajectory_errors(
    ts_est: np.ndarray, est_poses: np.ndarray, ts_gt: np.ndarray, gt_poses: np.ndarray
) -> tuple[TrajectoryErrors | None, str | None]:
    """Per-frame errors of an estimated trajectory ((N,), (N, 4, 4) c2w) against GT ((M,), (M, 4, 4)),
    or (None, why not: no GT, fewer than 3 matched frames, ...)."""
    metrics, ate = trajectory_metrics(ts_est, est_poses, ts_gt, gt_poses)
    if ate is None:
        return None, metrics.get("ate_reason") or "ATE not computable"
    est_r = np.asarray(est_poses)[ate.idx_est, :3, :3]
    ref = np.asarray(gt_poses)[ate.idx_ref]
    est_r = orientation_alignment(ref[:, :3, :3], est_r) @ est_r
    errors = TrajectoryErrors(
        times=np.asarray(ts_est)[ate.idx_est] - float(ts_est[0]),
        estimated=ate.aligned_positions,
        reference=ref[:, :3, 3],
        translation_m=ate.errors,
        rotation_deg=rotation_angle_deg(np.swapaxes(ref[:, :3, :3], 1, 2) @ est_r),
        reference_poses=ref,
    )
    return errors, None


def plot_axes(poses: np.ndarray) -> np.ndarray:
    """(3, 3) rows: two horizontal axes and up, for top and side views of a trajectory.

    Up is the cameras' mean "up" (-y in OpenCV axes: a hand-held or robot camera stays roughly
    level); the first horizontal axis is the direction the cameras moved most along.
    """
    up = -np.asarray(poses)[:, :3, 1].mean(axis=0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
    centred = poses[:, :3, 3] - poses[:, :3, 3].mean(axis=0)
    flat = centred - np.outer(centred @ up, up)
    if len(flat) > 1 and np.linalg.norm(flat) > 1e-9:
        first = np.linalg.svd(flat, full_matrices=False)[2][0]
    else:  # no horizontal motion: any horizontal axis
        first = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    first = first - (first @ up) * up
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(up, first), up])
