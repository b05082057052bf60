"""One rigid object's motion from the camera odometry on its pixels (pure functions).

Frames and poses, all (4, 4) float64:

* T_wc_k: camera k to world (the SLAM's tracked camera, known here);
* T_wo_k: object to world at frame k (what an :class:`ObjectTrack` holds);
* C_k = T_wo_k⁻¹ · T_wc_k: camera k to *object*, the camera's pose in a world where the object
  stands still.

Seen from its own frame the object is a static scene, so the existing dense odometry on the
object's pixels alone (reference = the object's last keyframe observation r, current = frame k)
estimates exactly the camera motion of that static scene: it returns T_ref_cur with
``C_k = C_r · T_ref_cur`` (the odometry's ``c2w_cur = c2w_ref @ T_ref_cur``, with "w" = object).
Hence, with the camera pose known,

    T_wo_k = T_wc_k · C_k⁻¹ = T_wc_k · T_ref_cur⁻¹ · C_r⁻¹ = T_wc_k · T_ref_cur⁻¹ · T_wc_r⁻¹ · T_wo_r,

and the initial guess of T_ref_cur for a predicted object pose T̂_wo_k is C_r⁻¹ · T̂_wo_k⁻¹ · T_wc_k.
A static object (T_wo_k = T_wo_r) gives T_ref_cur = T_wc_r⁻¹ T_wc_k, the camera's own motion.
"""

from __future__ import annotations

import math

import torch

from tivne.geometry import invert_pose, orthonormalize_pose, pose_difference, se3_exp, se3_log, skew


def camera_in_object(T_wo: torch.Tensor, T_wc: torch.Tensor) -> torch.Tensor:
    """C = T_wo⁻¹ · T_wc (4, 4): camera-to-object, the camera pose seen from the object."""
    return invert_pose(T_wo.double()) @ T_wc.double()


def object_pose(T_wc_cur: torch.Tensor, T_ref_cur: torch.Tensor, C_ref: torch.Tensor) -> torch.Tensor:
    """T_wo_k = T_wc_k · T_ref_cur⁻¹ · C_r⁻¹ (4, 4) float64 (see the module docstring).

    Args:
        T_wc_cur: (4, 4) the current camera-to-world pose.
        T_ref_cur: (4, 4) the odometry on the object's pixels (current -> reference camera).
        C_ref: (4, 4) camera-to-object pose of the reference observation.
    """
    # Back onto SE(3): every object pose is built from the previous ones (through C_ref), and inverses
    # taken as Rᵀ compound a rotation's non-orthogonality along that chain (float32 camera poses start it).
    return orthonormalize_pose(T_wc_cur.double() @ invert_pose(T_ref_cur.double()) @ invert_pose(C_ref.double()))


def odometry_init(T_wo_pred: torch.Tensor, T_wc_cur: torch.Tensor, C_ref: torch.Tensor) -> torch.Tensor:
    """The T_ref_cur (4, 4) that a predicted object pose T̂_wo_k implies: C_r⁻¹ · T̂_wo_k⁻¹ · T_wc_k."""
    return invert_pose(C_ref.double()) @ camera_in_object(T_wo_pred, T_wc_cur)


def interpolate_se3(A: torch.Tensor, B: torch.Tensor, s: float) -> torch.Tensor:
    """The pose (4, 4) a fraction ``s`` in [0, 1] along the geodesic from A to B (body frame):
    A · exp(s · log(A⁻¹ B)); s = 0 gives A, s = 1 gives B."""
    A, B = A.double(), B.double()
    return A @ se3_exp(float(s) * se3_log((invert_pose(A) @ B)[None])[0])


def centred_information(sigma_t: float, sigma_r: float, centre: torch.Tensor) -> torch.Tensor:
    """(6, 6) float64 information of an isotropic pose prior (σ_t metres, σ_r radians) on the
    motion of a body at ``centre`` (3,), in the tangent of a left twist δ = (v, w) about the origin.

    The body's own twist is ε = (v − [c]× w, w) (the velocity of its centre, its rotation), so
    Λ_δ = Mᵀ Λ_ε M with M = [[I, −[c]×], [0, I]]: a spin about the body's centre is penalised
    as a rotation only, not as the swing of the far-away origin about it.
    """
    M = torch.eye(6, dtype=torch.float64)
    M[:3, 3:] = -skew(centre.double())
    lam = torch.diag(torch.tensor([1.0 / sigma_t**2] * 3 + [1.0 / sigma_r**2] * 3, dtype=torch.float64))
    return M.T @ lam @ M


def within_motion_gate(T_wo: torch.Tensor, T_pred: torch.Tensor, dt: float, accel: float, angular_accel: float, sigmas: float) -> bool:
    """Whether an object pose T_wo (4, 4) is within ``sigmas`` σ of its constant-velocity prediction
    T_pred (4, 4), with the motion prior's σ over ``dt`` seconds (σ_t = ½ a Δt² metres at the object's
    origin, σ_r = ½ α Δt² radians; ``accel`` a m/s², ``angular_accel`` α rad/s²), translation and
    rotation apart. No gate (True) without a prior (a or α <= 0) or without a time step."""
    if accel <= 0 or angular_accel <= 0 or dt <= 0:
        return True
    moved, degrees = pose_difference(T_pred, T_wo)  # |T_pred⁻¹ T_wo|: the origin's shift, the turn
    return moved <= sigmas * 0.5 * accel * dt * dt and math.radians(degrees) <= sigmas * 0.5 * angular_accel * dt * dt
