"""Evaluation metrics as pure functions: trajectory (ATE, RPE), image (MSE, PSNR, SSIM, LPIPS) and
surface (accuracy, completion, Chamfer-L1, completion ratio, ghost fraction).

Input types:
    * trajectory and surface metrics accept numpy arrays or torch tensors (any device) and compute
      in numpy float64; they return python floats / numpy arrays.
    * image metrics accept torch tensors (or numpy arrays) of shape (H, W, 3) or (B, 3, H, W), float
      in [0, 1], and compute in torch on the input's device; they return python floats.

Poses are camera-to-world (c2w) 4x4 matrices; distances are in metres, angles in degrees.
Metric dictionaries use the flat snake_case keys of ``metrics.json`` (``ate_rmse_m``, ``psnr_db``, ...).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from scipy.spatial import cKDTree
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
# Association
# --------------------------------------------------------------------------------------------------


def associate_by_index(n_est: int, n_ref: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair the i-th estimate with the i-th reference pose, for the first ``min(n_est, n_ref)``.

    Returns:
        idx_est (K,) and idx_ref (K,) int64, both ``arange(K)``.
    """
    k = min(int(n_est), int(n_ref))
    return np.arange(k, dtype=np.int64), np.arange(k, dtype=np.int64)


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
    est = _as_np64(est_poses)
    ref = _as_np64(ref_poses)
    _check_poses(est, "est_poses")
    _check_poses(ref, "ref_poses")
    if len(est) != len(ref):
        raise ValueError(f"absolute_trajectory_error: {len(est)} estimated but {len(ref)} reference poses")
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
    est = _as_np64(est_poses)
    ref = _as_np64(ref_poses)
    _check_poses(est, "est_poses")
    _check_poses(ref, "ref_poses")
    if len(est) != len(ref):
        raise ValueError(f"relative_pose_error: {len(est)} estimated but {len(ref)} reference poses")
    if delta < 1 or len(est) <= delta:
        raise ValueError(f"relative_pose_error: need more than delta={delta} poses, got {len(est)}")
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


# --------------------------------------------------------------------------------------------------
# Image metrics
# --------------------------------------------------------------------------------------------------


def _as_bchw(img: ArrayLike) -> torch.Tensor:
    """(H, W, 3) or (B, 3, H, W) -> (B, 3, H, W) float tensor (float64 stays float64)."""
    t = torch.as_tensor(img)
    if not t.is_floating_point():
        raise ValueError(f"image metrics need float images in [0, 1], got dtype {t.dtype}")
    if t.ndim == 3 and t.shape[-1] == 3:
        return t.permute(2, 0, 1)[None]
    if t.ndim == 4 and t.shape[1] == 3:
        return t
    raise ValueError(f"image metrics need (H, W, 3) or (B, 3, H, W) images, got shape {tuple(t.shape)}")


def _as_b1hw_mask(mask: ArrayLike | None, like: torch.Tensor) -> torch.Tensor | None:
    """(H, W), (B, H, W) or (B, 1, H, W) bool -> (B, 1, H, W) bool broadcastable against ``like``."""
    if mask is None:
        return None
    m = torch.as_tensor(mask, device=like.device).bool()
    if m.ndim == 2:
        m = m[None, None]
    elif m.ndim == 3:
        m = m[:, None]
    b, _, h, w = like.shape
    if m.ndim != 4 or m.shape[1] != 1 or m.shape[-2:] != (h, w) or m.shape[0] not in (1, b):
        raise ValueError(f"mask shape {tuple(torch.as_tensor(mask).shape)} does not fit images of shape {tuple(like.shape)}")
    return m.expand(b, 1, h, w)


def _pair(pred: ArrayLike, gt: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
    p, g = _as_bchw(pred), _as_bchw(gt)
    if p.shape != g.shape:
        raise ValueError(f"pred shape {tuple(p.shape)} != gt shape {tuple(g.shape)} (after layout to B,3,H,W)")
    g = g.to(device=p.device, dtype=p.dtype)
    return p, g


def _per_image_mse(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor | None) -> torch.Tensor:
    """(B,) mean squared error per image over valid pixels and channels (NaN where none are valid)."""
    sq = (p - g) ** 2
    if m is None:
        return sq.flatten(1).mean(1)
    w = m.to(sq.dtype).expand_as(sq)
    return (sq * w).flatten(1).sum(1) / w.flatten(1).sum(1)  # 0 / 0 = NaN for an empty mask


def mse(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Mean squared error over all valid pixels, channels and images.

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        mask: optional (H, W), (B, H, W) or (B, 1, H, W) bool, True where the pixel counts.
    Returns:
        MSE; NaN when the mask selects no pixel.
    """
    p, g = _pair(pred, gt)
    m = _as_b1hw_mask(mask, p)
    sq = (p - g) ** 2
    if m is None:
        return float(sq.mean())
    w = m.to(sq.dtype).expand_as(sq)
    return float((sq * w).sum() / w.sum())


def psnr(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(max_val^2 / MSE)``.

    For a batch, the PSNR of every image is computed from its own MSE and the mean over images is
    returned (the usual per-frame averaging of neural SLAM evaluations).

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        mask: optional (H, W), (B, H, W) or (B, 1, H, W) bool, True where the pixel counts.
        max_val: peak signal value.
    Returns:
        PSNR in dB. ``math.inf`` when an image matches exactly (MSE = 0; not capped — write it as
        null in JSON); NaN when the mask selects no pixel in some image.
    """
    p, g = _pair(pred, gt)
    per_image = _per_image_mse(p, g, _as_b1hw_mask(mask, p)).double()
    vals = 10.0 * torch.log10(max_val**2 / per_image)  # mse = 0 -> +inf
    return float(vals.mean())


def ssim(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None, window_size: int = 11) -> float:
    """Structural similarity (Gaussian window, kornia.metrics.ssim, data range 1).

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        mask: optional (H, W), (B, H, W) or (B, 1, H, W) bool; when given, the SSIM map is averaged
            over the selected pixels only (windows still see their unmasked neighbours).
        window_size: Gaussian window size (odd).
    Returns:
        Mean SSIM in [-1, 1] (1 for identical images); NaN when the mask selects no pixel.
    """
    import kornia

    p, g = _pair(pred, gt)
    m = _as_b1hw_mask(mask, p)
    smap = kornia.metrics.ssim(p, g, window_size=window_size, max_val=1.0)  # (B, 3, H, W)
    if m is None:
        return float(smap.mean())
    w = m.to(smap.dtype).expand_as(smap)
    return float((smap * w).sum() / w.sum())


# Torchvision backbone files that LPIPS needs in the torch hub cache (never downloaded here).
_LPIPS_BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}


def lpips_available(net: str = "alex") -> tuple[bool, str]:
    """Whether :func:`lpips` can run offline.

    Needs the ``lpips`` and ``torchvision`` packages and the torchvision backbone weights already in
    the torch hub cache (``$TORCH_HOME/hub/checkpoints``); nothing is downloaded.

    Returns:
        (True, "") or (False, reason).
    """
    if net not in _LPIPS_BACKBONE_FILES:
        return False, f"unsupported LPIPS backbone {net!r} (use one of {sorted(_LPIPS_BACKBONE_FILES)})"
    try:
        import torchvision  # noqa: F401
    except Exception as e:  # ImportError, or a torchvision built for another torch
        return False, f"torchvision not importable ({type(e).__name__}: {e})"
    try:
        import lpips as _lpips  # noqa: F401
    except Exception as e:
        return False, f"lpips package not importable ({type(e).__name__}: {e})"
    weights = Path(torch.hub.get_dir()) / "checkpoints" / _LPIPS_BACKBONE_FILES[net]
    if not weights.is_file():
        return False, f"LPIPS backbone weights not in the local torch hub cache ({weights.name}); not downloading"
    return True, ""


@functools.lru_cache(maxsize=4)
def _lpips_model(net: str, device: str) -> torch.nn.Module:
    import lpips as _lpips

    # The backbone weights are in the hub cache (checked by lpips_available), so torchvision loads
    # them from disk; the linear calibration layers ship inside the lpips package.
    model = _lpips.LPIPS(net=net, verbose=False).eval().to(device)
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def lpips(pred: ArrayLike, gt: ArrayLike, net: str = "alex") -> tuple[float | None, str]:
    """Learned perceptual image patch similarity (lower is better), averaged over the batch.

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        net: backbone, "alex" (default, as most neural SLAM papers) or "vgg".
    Returns:
        (value, "") or (None, reason) when :func:`lpips_available` says it cannot run offline.
    """
    ok, reason = lpips_available(net)
    if not ok:
        return None, reason
    p, g = _pair(pred, gt)
    model = _lpips_model(net, str(p.device))
    with torch.no_grad():
        d = model(p.float() * 2 - 1, g.float() * 2 - 1)  # LPIPS expects [-1, 1]
    return float(d.mean()), ""


# --------------------------------------------------------------------------------------------------
# Surface metrics
# --------------------------------------------------------------------------------------------------


def _as_points(x: ArrayLike, name: str) -> np.ndarray:
    p = _as_np64(x)
    if p.size == 0:
        return p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    return p


def sample_mesh_surface(mesh, n: int, seed: int = 0) -> np.ndarray:
    """Area-weighted uniform samples on a triangle mesh (``trimesh.sample.sample_surface``).

    Args:
        mesh: ``trimesh.Trimesh``.
        n: number of samples.
        seed: RNG seed (same seed, same mesh -> same points).
    Returns:
        (n, 3) float64 points; (0, 3) when the mesh has no faces or zero area.
    """
    import trimesh

    if len(mesh.faces) == 0 or not mesh.area > 0 or n <= 0:
        return np.zeros((0, 3))
    points, _ = trimesh.sample.sample_surface(mesh, int(n), seed=seed)
    return np.asarray(points, dtype=np.float64)


def nearest_distances(query: ArrayLike, points: ArrayLike) -> np.ndarray:
    """Distance from every query point to its nearest neighbour in ``points`` (cKDTree).

    Args:
        query: (N, 3); points: (M, 3).
    Returns:
        (N,) metres; all ``inf`` when ``points`` is empty.
    """
    q = _as_points(query, "query")
    p = _as_points(points, "points")
    if len(p) == 0:
        return np.full(len(q), np.inf)
    if len(q) == 0:
        return np.zeros(0)
    d, _ = cKDTree(p).query(q, k=1)
    return np.asarray(d, dtype=np.float64)


def mesh_metrics(pred_points: ArrayLike, gt_points: ArrayLike, threshold: float = 0.05) -> dict[str, float]:
    """Surface accuracy / completion between reconstructed and ground-truth surface samples.

    Args:
        pred_points: (N, 3) samples of the reconstructed surface (see :func:`sample_mesh_surface`).
        gt_points: (M, 3) samples of the ground-truth surface, M > 0.
        threshold: distance in metres under which a GT point counts as completed.
    Returns:
        ``accuracy_m``: mean distance pred -> nearest gt; ``completion_m``: mean distance gt -> nearest
        pred; ``chamfer_l1_m``: their mean; ``completion_ratio``: share of gt points within
        ``threshold`` of pred. With no predicted points: accuracy NaN (nothing to measure),
        completion and Chamfer inf, completion ratio 0.
    Raises:
        ValueError: empty ground truth.
    """
    pred = _as_points(pred_points, "pred_points")
    gt = _as_points(gt_points, "gt_points")
    if len(gt) == 0:
        raise ValueError("mesh_metrics: ground-truth point set is empty")
    if len(pred) == 0:
        return {"accuracy_m": math.nan, "completion_m": math.inf, "chamfer_l1_m": math.inf, "completion_ratio": 0.0}
    acc = float(nearest_distances(pred, gt).mean())
    d_gt = nearest_distances(gt, pred)
    comp = float(d_gt.mean())
    return {
        "accuracy_m": acc,
        "completion_m": comp,
        "chamfer_l1_m": 0.5 * (acc + comp),
        "completion_ratio": float((d_gt < threshold).mean()),
    }


def ghost_fraction(pred_points: ArrayLike, gt_points_at_t: ArrayLike, threshold: float = 0.05) -> float:
    """Share of reconstructed surface points at time t farther than ``threshold`` from every GT point at t.

    Measures "ghost" geometry (e.g. a dynamic object left behind where it used to be).

    Args:
        pred_points: (N, 3) samples of the surface reconstructed for time t.
        gt_points_at_t: (M, 3) samples of the true surface at time t.
        threshold: metres.
    Returns:
        Fraction in [0, 1]; NaN when there are no predicted points; 1 when the GT is empty and the
        prediction is not.
    """
    pred = _as_points(pred_points, "pred_points")
    if len(pred) == 0:
        return math.nan
    d = nearest_distances(pred, gt_points_at_t)
    return float((d > threshold).mean())
