"""Trajectory metrics as pure functions: association, Umeyama alignment, ATE and RPE.

Inputs are numpy arrays or torch tensors (any device); computation is in numpy float64 and the
results are python floats / numpy arrays. Poses are camera-to-world (c2w) 4x4 matrices; distances in
metres, angles in degrees. Metric dictionaries use the flat snake_case keys of ``metrics.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from scipy.spatial.transform import Rotation

# The one timestamp association (TUM associate.py, |dt| <= max_diff) lives in the data layer.
from data_modules.timestamps import associate_by_timestamp

ArrayLike = np.ndarray | torch.Tensor
Alignment = Literal["se3", "sim3", "none"]


def _as_np64(x: ArrayLike) -> np.ndarray:
    """Any array / tensor -> numpy float64 (detached, on the CPU)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# Alignment and trajectory errors
# --------------------------------------------------------------------------------------------------


def umeyama_alignment(
    src: ArrayLike, dst: ArrayLike, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (Umeyama 1991) with ``dst ≈ s R src + t``.

    A reflection in the SVD solution is replaced by the best proper rotation (det R = +1). For
    degenerate inputs (collinear or coincident points) the rotation is not unique; an optimal one is
    still returned, so the residual error stays well defined.

    Args:
        src: (N, 3) points.
        dst: (N, 3) corresponding points.
        with_scale: also estimate the scale ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).
    Returns:
        R (3, 3), t (3,) float64 and s (float).
    Raises:
        ValueError: shape mismatch, no points, or ``with_scale`` with all ``src`` points coincident.
    """
    x = _as_np64(src)
    y = _as_np64(dst)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"umeyama_alignment: need two (N, 3) arrays, got {x.shape} and {y.shape}")
    n = x.shape[0]
    if n == 0:
        raise ValueError("umeyama_alignment: no points to align")
    mean_x, mean_y = x.mean(0), y.mean(0)
    xc, yc = x - mean_x, y - mean_y
    var_x = float((xc**2).sum() / n)
    cov = yc.T @ xc / n  # (3, 3) = E[(y - mu_y)(x - mu_x)^T]
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0  # reflection -> closest proper rotation
    R = U @ S @ Vt
    if with_scale:
        if var_x <= np.finfo(np.float64).tiny:
            raise ValueError("umeyama_alignment: source points coincide, scale is undefined")
        s = float(np.trace(np.diag(d) @ S) / var_x)
    else:
        s = 1.0
    t = mean_y - s * R @ mean_x
    return R, t, s


def _check_poses(poses: np.ndarray, name: str) -> None:
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected (N, 4, 4) poses, got shape {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError(f"{name}: poses contain NaN or inf")


def _paired_poses(est_poses: ArrayLike, ref_poses: ArrayLike, caller: str) -> tuple[np.ndarray, np.ndarray]:
    """Checked (N, 4, 4) float64 estimated and reference poses, as many of each."""
    est = _as_np64(est_poses)
    ref = _as_np64(ref_poses)
    _check_poses(est, "est_poses")
    _check_poses(ref, "ref_poses")
    if len(est) != len(ref):
        raise ValueError(f"{caller}: {len(est)} estimated but {len(ref)} reference poses")
    return est, ref


@dataclass(frozen=True)
class ATEResult:
    """Absolute trajectory error (translation part) after aligning the estimate to the reference.

    Attributes:
        rmse, mean, median, std, max: statistics of ``errors`` in metres (std is the population std).
        errors: (N,) per-pose translation error in metres.
        rotation: (3, 3), translation: (3,), scale: the alignment, ``ref ≈ s R est + t``.
        align: "se3", "sim3" or "none".
        aligned_positions: (N, 3) estimated camera positions after alignment.
        idx_est, idx_ref: (N,) indices of the associated poses in the original trajectories.
    """

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    errors: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    scale: float
    align: str
    aligned_positions: np.ndarray
    idx_est: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    idx_ref: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def num_poses(self) -> int:
        return int(len(self.errors))

    @property
    def alignment_matrix(self) -> np.ndarray:
        """(4, 4) similarity [[s R, t], [0, 1]] that maps estimated positions onto the reference."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def as_metrics(self, prefix: str = "ate") -> dict[str, float]:
        """Flat ``metrics.json`` keys: ``{prefix}_rmse_m``, ``_mean_m``, ``_median_m``, ``_std_m``, ``_max_m``."""
        return {
            f"{prefix}_rmse_m": self.rmse,
            f"{prefix}_mean_m": self.mean,
            f"{prefix}_median_m": self.median,
            f"{prefix}_std_m": self.std,
            f"{prefix}_max_m": self.max,
        }


def absolute_trajectory_error(
    est_poses: ArrayLike, ref_poses: ArrayLike, align: Alignment = "se3"
) -> ATEResult:
    """ATE of already associated poses (the i-th estimate belongs to the i-th reference pose).

    Only camera positions enter the alignment and the error, as in TUM's ``evaluate_ate`` and evo's
    ``APE`` with ``PoseRelation.translation_part``.

    Args:
        est_poses: (N, 4, 4) estimated c2w poses.
        ref_poses: (N, 4, 4) reference (ground-truth) c2w poses.
        align: "se3" (rotation + translation), "sim3" (+ scale) or "none".
    Returns:
        :class:`ATEResult`.
    Raises:
        ValueError: shape mismatch, no poses, non-finite poses or an unknown ``align``.
    """
    est, ref = _paired_poses(est_poses, ref_poses, "absolute_trajectory_error")
    if len(est) == 0:
        raise ValueError("absolute_trajectory_error: no poses")
    p_est, p_ref = est[:, :3, 3], ref[:, :3, 3]
    if align == "none":
        R, t, s = np.eye(3), np.zeros(3), 1.0
    elif align in ("se3", "sim3"):
        R, t, s = umeyama_alignment(p_est, p_ref, with_scale=align == "sim3")
    else:
        raise ValueError(f"absolute_trajectory_error: align must be 'se3', 'sim3' or 'none', got {align!r}")
    aligned = s * p_est @ R.T + t
    errors = np.linalg.norm(aligned - p_ref, axis=1)
    idx = np.arange(len(est), dtype=np.int64)
    return ATEResult(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(np.mean(errors)),
        median=float(np.median(errors)),
        std=float(np.std(errors)),
        max=float(np.max(errors)),
        errors=errors,
        rotation=R,
        translation=t,
        scale=float(s),
        align=align,
        aligned_positions=aligned,
        idx_est=idx,
        idx_ref=idx.copy(),
    )


def ate_from_trajectories(
    ts_est: ArrayLike,
    est_poses: ArrayLike,
    ts_ref: ArrayLike,
    ref_poses: ArrayLike,
    max_diff: float = 0.02,
    align: Alignment = "se3",
) -> ATEResult:
    """ATE of two timestamped trajectories: associate by timestamp, then :func:`absolute_trajectory_error`.

    Args:
        ts_est: (N,) seconds; est_poses: (N, 4, 4) c2w.
        ts_ref: (M,) seconds; ref_poses: (M, 4, 4) c2w.
        max_diff: association tolerance in seconds.
        align: "se3", "sim3" or "none".
    Returns:
        :class:`ATEResult` over the K matched pairs, with ``idx_est`` / ``idx_ref`` set.
    Raises:
        ValueError: no timestamps match within ``max_diff``.
    """
    est = _as_np64(est_poses)
    ref = _as_np64(ref_poses)
    i_est, i_ref = associate_by_timestamp(ts_est, ts_ref, max_diff)
    if len(i_est) == 0:
        raise ValueError(f"ate_from_trajectories: no timestamps match within max_diff={max_diff} s")
    res = absolute_trajectory_error(est[i_est], ref[i_ref], align=align)
    return replace(res, idx_est=i_est, idx_ref=i_ref)


@dataclass(frozen=True)
class RPEResult:
    """Relative pose error over a fixed frame delta.

    Attributes:
        trans_rmse_m, trans_mean_m: statistics of the translation drift per delta, metres.
        rot_rmse_deg, rot_mean_deg: statistics of the rotation drift per delta, degrees.
        trans_errors: (N - delta,) metres; rot_errors: (N - delta,) degrees.
        delta: frame delta.
    """

    trans_rmse_m: float
    trans_mean_m: float
    rot_rmse_deg: float
    rot_mean_deg: float
    trans_errors: np.ndarray
    rot_errors: np.ndarray
    delta: int

    def as_metrics(self, prefix: str = "rpe") -> dict[str, float]:
        """Flat keys ``{prefix}_trans_rmse_m``, ``_trans_mean_m``, ``_rot_rmse_deg``, ``_rot_mean_deg``."""
        return {
            f"{prefix}_trans_rmse_m": self.trans_rmse_m,
            f"{prefix}_trans_mean_m": self.trans_mean_m,
            f"{prefix}_rot_rmse_deg": self.rot_rmse_deg,
            f"{prefix}_rot_mean_deg": self.rot_mean_deg,
        }


def _delta_pairs(est_poses: ArrayLike, ref_poses: ArrayLike, delta: int, caller: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_paired_poses` with more than ``delta`` (>= 1) of each."""
    est, ref = _paired_poses(est_poses, ref_poses, caller)
    if delta < 1 or len(est) <= delta:
        raise ValueError(f"{caller}: need more than delta={delta} poses, got {len(est)}")
    return est, ref


def relative_pose_error(est_poses: ArrayLike, ref_poses: ArrayLike, delta: int = 1) -> RPEResult:
    """RPE of associated poses for consecutive pairs ``(i, i + delta)`` (TUM / evo definition).

    ``E_i = (Q_i^-1 Q_{i+delta})^-1 (P_i^-1 P_{i+delta})`` with reference Q and estimate P; the
    translation error is ``|trans(E_i)|`` and the rotation error the angle of ``rot(E_i)``. No alignment
    is needed (RPE is invariant to a global rigid transform; not to scale). All overlapping pairs
    ``i = 0 .. N - 1 - delta`` are used, as TUM's ``evaluate_rpe`` and evo with ``all_pairs=True``
    (evo's default takes non-overlapping pairs only).

    Args:
        est_poses: (N, 4, 4) c2w; ref_poses: (N, 4, 4) c2w.
        delta: frame delta, >= 1.
    Returns:
        :class:`RPEResult`.
    Raises:
        ValueError: shape mismatch or fewer than ``delta + 1`` poses.
    """
    est, ref = _delta_pairs(est_poses, ref_poses, delta, "relative_pose_error")
    rel_est = np.linalg.inv(est[:-delta]) @ est[delta:]
    rel_ref = np.linalg.inv(ref[:-delta]) @ ref[delta:]
    E = np.linalg.inv(rel_ref) @ rel_est
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    return RPEResult(
        trans_rmse_m=float(np.sqrt(np.mean(trans**2))),
        trans_mean_m=float(np.mean(trans)),
        rot_rmse_deg=float(np.sqrt(np.mean(rot**2))),
        rot_mean_deg=float(np.mean(rot)),
        trans_errors=trans,
        rot_errors=rot,
        delta=int(delta),
    )


@dataclass(frozen=True)
class RelativeMotionMap:
    """The linear map that best takes the reference's relative translations to the estimate's.

    A tracker's own error is mostly random from pair to pair; a calibration or ground-truth mismatch
    (another focal length, depth scale, or camera frame behind the reference poses) is one linear map
    for all pairs. Two independent trackers sharing the same map point at the reference, not at
    either tracker.

    Attributes:
        matrix: (3, 3) A minimising sum |t_est - A t_ref|² over the pairs (camera frame of the pair's first pose).
        singular_values: (3,) of A, largest first (all 1 for a pure rotation or the identity).
        rotation_deg: angle of A's closest rotation (U Vᵀ of its SVD).
        trans_rmse_m: RMS of |t_est - t_ref| over the pairs; fit_rmse_m: of |t_est - A t_ref|.
        delta: frame delta of the pairs; pairs: their number.
    """

    matrix: np.ndarray
    singular_values: np.ndarray
    rotation_deg: float
    trans_rmse_m: float
    fit_rmse_m: float
    delta: int
    pairs: int


def relative_motion_map(est_poses: ArrayLike, ref_poses: ArrayLike, delta: int = 30) -> RelativeMotionMap:
    """:class:`RelativeMotionMap` of associated poses over the pairs ``(i, i + delta)``.

    Args:
        est_poses: (N, 4, 4) c2w; ref_poses: (N, 4, 4) c2w; delta >= 1, fewer than N.
    Raises:
        ValueError: shape mismatch, too few poses, or reference translations that span no 3-D space.
    """
    est, ref = _delta_pairs(est_poses, ref_poses, delta, "relative_motion_map")
    t_est = (np.linalg.inv(est[:-delta]) @ est[delta:])[:, :3, 3]
    t_ref = (np.linalg.inv(ref[:-delta]) @ ref[delta:])[:, :3, 3]
    solution, _, rank, _ = np.linalg.lstsq(t_ref, t_est, rcond=None)
    if rank < 3:
        raise ValueError("relative_motion_map: the reference's relative translations span fewer than 3 dimensions")
    A = solution.T
    U, S, Vt = np.linalg.svd(A)
    closest = U @ Vt
    if np.linalg.det(closest) < 0:  # a reflection is no camera motion: flip the weakest axis
        closest = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return RelativeMotionMap(
        matrix=A,
        singular_values=S,
        rotation_deg=float(np.degrees(Rotation.from_matrix(closest).magnitude())),
        trans_rmse_m=float(np.sqrt(np.mean(np.sum((t_est - t_ref) ** 2, axis=1)))),
        fit_rmse_m=float(np.sqrt(np.mean(np.sum((t_est - t_ref @ A.T) ** 2, axis=1)))),
        delta=int(delta),
        pairs=len(t_ref),
    )
