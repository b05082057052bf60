"""Rigid-pose helpers the readers need: quaternions, poses from files, SO(3) projection, SLERP.

Conventions: poses are 4x4 matrices (camera-to-world for camera poses); quaternions are in TUM
order ``(qx, qy, qz, qw)``, scalar last. Pure functions on batched tensors (shapes in docstrings);
:func:`interpolate_poses` takes its time axes as numpy float64 arrays, as the readers hold them.
"""

from __future__ import annotations

import numpy as np
import torch

# A query this close to a sample time takes that sample's pose. Trajectory files round timestamps
# (6 decimals is usual) while frame times may not be (index / fps), so the last frame can land a
# microsecond after the last pose; 0.1 ms is far above that rounding and far below a frame period.
TIME_TOLERANCE_S = 1e-4
# Seconds over which pose_on_track reads an end's velocity (so one noisy pose does not set it).
VELOCITY_BASELINE_S = 0.1


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Quaternions (..., 4) in TUM order (qx, qy, qz, qw) -> rotation matrices (..., 3, 3).

    The quaternion is normalised first, so slightly off-unit file values are accepted.
    """
    q = q / q.norm(dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    row0 = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1)
    row1 = torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1)
    row2 = torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)
    return torch.stack([row0, row1, row2], dim=-2)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (qx, qy, qz, qw) with qw >= 0.

    Uses the numerically stable branch on the largest diagonal term (Shepperd's method).
    """
    m = R
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1], 1 + trace], -1),
            torch.stack([1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] - m[..., 1, 2]], -1),
            torch.stack([m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1], m[..., 0, 2] - m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], m[..., 1, 0] - m[..., 0, 1]], -1),
        ],
        dim=-2,
    )  # (..., 4 candidates, 4) each proportional to (x, y, z, w)
    key = torch.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = key.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def pose_from_tq(t: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Translation (..., 3) + quaternion (..., 4) (qx, qy, qz, qw) -> (..., 4, 4) pose in t's dtype."""
    T = torch.zeros(*t.shape[:-1], 4, 4, dtype=t.dtype, device=t.device)
    T[..., :3, :3] = quat_to_matrix(q.to(t.dtype))
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def orthonormalize_pose(T: torch.Tensor) -> torch.Tensor:
    """Project the rotation block of (..., 4, 4) transforms onto SO(3); keep the translation.

    The nearest rotation in Frobenius norm (SVD, R = U Vᵀ with the sign of U's last column chosen so
    that det R = +1). Pose chains such as T1 · T2⁻¹ · T1 (inverse taken as Rᵀ) double a rotation's
    non-orthogonality every time, and hand-typed calibration matrices are rarely orthonormal.

    Args:
        T: (..., 4, 4) float32 or float64.
    Returns:
        (..., 4, 4) in T's dtype with last row (0, 0, 0, 1).
    """
    # float64 inside: the SVD of a nearly orthonormal float32 matrix loses the digits we want to fix.
    U, _, Vh = torch.linalg.svd(T[..., :3, :3].double())
    # where(), not sign(): a det of exactly 0 (rank-deficient input) must not zero a column.
    d = torch.where(torch.det(U @ Vh) < 0, -1.0, 1.0).to(U.dtype)
    U = torch.cat([U[..., :, :2], U[..., :, 2:] * d[..., None, None]], dim=-1)
    out = T.clone()
    out[..., :3, :3] = (U @ Vh).to(T.dtype)
    out[..., 3, :3] = 0
    out[..., 3, 3] = 1
    return out


def slerp_quat(qa: torch.Tensor, qb: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    Args:
        qa, qb: (..., 4) unit quaternions (any order of components, as long as both agree).
        s: (...) fraction in [0, 1]; 0 gives qa, 1 gives qb (up to sign).
    Returns:
        (..., 4) unit quaternions.
    """
    dot = (qa * qb).sum(-1)
    qb = torch.where(dot[..., None] < 0, -qb, qb)  # q and -q are the same rotation: take the short way
    dot = dot.abs().clamp(max=1.0)
    theta = torch.arccos(dot)
    nearly_equal = dot > 0.9995  # sin(theta) ~ 0: plain lerp is exact enough and avoids 0/0
    sin_theta = torch.where(nearly_equal, torch.ones_like(theta), torch.sin(theta))
    wa = torch.where(nearly_equal, 1 - s, torch.sin((1 - s) * theta) / sin_theta)
    wb = torch.where(nearly_equal, s, torch.sin(s * theta) / sin_theta)
    q = wa[..., None] * qa + wb[..., None] * qb
    return q / q.norm(dim=-1, keepdim=True)


def interpolate_poses(
    times: np.ndarray,
    poses: torch.Tensor,
    query: np.ndarray,
    max_gap: float | None = None,
    tolerance: float = TIME_TOLERANCE_S,
) -> tuple[torch.Tensor, np.ndarray]:
    """Poses at ``query`` times: SLERP rotation + linear translation between bracketing samples.

    Args:
        times: (N,) strictly increasing sample times [s].
        poses: (N, 4, 4) poses at ``times``.
        query: (M,) times to evaluate [s].
        max_gap: the bracketing samples may be at most this far apart (None = any).
        tolerance: a query within this many seconds of a sample time takes that sample's pose and
            is always valid, also just outside [times[0], times[-1]] (rounded file timestamps).
    Returns:
        (M, 4, 4) float64 poses (identity where invalid) and (M,) bool ``valid``: False outside
        [times[0] - tolerance, times[-1] + tolerance] or inside a longer gap. Nothing is extrapolated.
    """
    times = np.asarray(times, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    poses = torch.as_tensor(poses, dtype=torch.float64)
    m, n = len(query), len(times)
    out = torch.eye(4, dtype=torch.float64).repeat(m, 1, 1)
    valid = np.zeros(m, dtype=bool)
    if n == 0 or m == 0:
        return out, valid
    after = np.searchsorted(times, query, side="left")  # first sample at or after each query
    lo, hi = np.clip(after - 1, 0, n - 1), np.clip(after, 0, n - 1)
    nearest = np.where(np.abs(times[lo] - query) <= np.abs(times[hi] - query), lo, hi)
    snap = np.abs(times[nearest] - query) <= tolerance
    inside = (after > 0) & (after < n) & ~snap
    if max_gap is not None:
        inside &= (times[hi] - times[lo]) <= max_gap
    out[torch.from_numpy(snap)] = poses[torch.from_numpy(nearest[snap])]
    if inside.any():
        a, b = lo[inside], hi[inside]
        s = torch.from_numpy((query[inside] - times[a]) / (times[b] - times[a]))  # (K,) in (0, 1)
        a, b, rows = torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(inside)
        quats = matrix_to_quat(poses[:, :3, :3])
        out[rows, :3, :3] = quat_to_matrix(slerp_quat(quats[a], quats[b], s))
        out[rows, :3, 3] = (1 - s)[:, None] * poses[a, :3, 3] + s[:, None] * poses[b, :3, 3]
    valid[snap | inside] = True
    return out, valid


def rotation_vector(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> axis · angle (..., 3) (the SO(3) log; angle in [0, π])."""
    q = matrix_to_quat(R)  # (..., 4) unit, qw >= 0 is not guaranteed: take the short way
    q = torch.where(q[..., 3:] < 0, -q, q)
    s = q[..., :3].norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., 3:])
    return torch.where(s > 1e-12, q[..., :3] * (angle / s.clamp_min(1e-12)), 2.0 * q[..., :3])


def rotation_from_vector(w: torch.Tensor) -> torch.Tensor:
    """Axis · angle (..., 3) -> rotation matrices (..., 3, 3) (the SO(3) exp)."""
    half = 0.5 * w.norm(dim=-1, keepdim=True)
    scale = torch.where(half > 1e-12, torch.sin(half) / half.clamp_min(1e-12), torch.ones_like(half) - half**2 / 6)
    return quat_to_matrix(torch.cat([0.5 * w * scale, torch.cos(half)], dim=-1))


def _velocity(times: np.ndarray, poses: torch.Tensor, end: int, inner: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(ω, v), each (3,) per second, between samples ``inner`` and ``end`` (either order in time):
    R_end = exp(ω·Δt)·R_inner, t_end = t_inner + v·Δt."""
    span = times[end] - times[inner]
    A, B = poses[inner], poses[end]
    return rotation_vector(B[:3, :3] @ A[:3, :3].T) / span, (B[:3, 3] - A[:3, 3]) / span


def _carried(times: np.ndarray, poses: torch.Tensor, end: int, velocity: tuple[torch.Tensor, torch.Tensor], t: float) -> torch.Tensor:
    """Sample ``end`` (4, 4) carried on to time ``t`` at ``velocity`` (ω, v) (:func:`_velocity`):
    translation and rotation apart, t(s) = t_e + v·s and R(s) = exp(ω·s)·R_e."""
    omega, v = velocity
    out = poses[end].clone()
    out[:3, :3] = rotation_from_vector(omega * (t - times[end])) @ poses[end, :3, :3]
    out[:3, 3] = poses[end, :3, 3] + v * (t - times[end])
    return out


def _baseline_partner(times: np.ndarray, end: int, baseline: float, direction: int) -> int:
    """The sample about ``baseline`` seconds from sample ``end`` towards ``direction`` (-1 earlier,
    +1 later), at least one sample away (clipped to the array)."""
    n = len(times)
    if direction < 0:
        return int(np.clip(np.searchsorted(times, times[end] - baseline, side="right") - 1, 0, end - 1))
    return int(np.clip(np.searchsorted(times, times[end] + baseline, side="left"), end + 1, n - 1))


def _end_partners(times: np.ndarray, end: int, baseline: float, direction: int) -> tuple[int | None, int | None]:
    """For a gap's ``end`` (``direction`` -1: the gap's start, looking back; +1: its end, looking on),
    the sample that measures the end's spin (:func:`_baseline_partner`, when within 2·baseline) and the
    one that measures its velocity: that one, else the next sample when within 2·baseline (a short run
    between two gaps: its position moves enough to read, its spin too little); None where there is none."""
    near = end + direction
    if not 0 <= near < len(times):
        return None, None
    spin = _baseline_partner(times, end, baseline, direction)
    spin = spin if abs(times[spin] - times[end]) <= 2 * baseline else None
    return spin, spin if spin is not None else (near if abs(times[near] - times[end]) <= 2 * baseline else None)


def hermite(p0: torch.Tensor, v0: torch.Tensor, p1: torch.Tensor, v1: torch.Tensor, span: float, s: float) -> torch.Tensor:
    """The cubic (3,) through p0 (3,) at s = 0 and p1 (3,) at s = 1 with velocities v0, v1 (3,) per
    second over ``span`` seconds: exact for any motion of constant acceleration (a body that slows,
    turns back and comes again), not only for a constant velocity."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * span * v0 + (3 * s2 - 2 * s3) * p1 + (s3 - s2) * span * v1


def pose_on_track(times: np.ndarray, poses: torch.Tensor, t: float, baseline: float = VELOCITY_BASELINE_S,
                  pivot: torch.Tensor | None = None) -> torch.Tensor:
    """The pose (4, 4) float64 of a sampled trajectory at any time ``t``.

    Between samples up to ``baseline`` apart: :func:`interpolate_poses` (SLERP + linear). Outside
    [times[0], times[-1]]: the end pose continued at the end's velocity, translation and rotation
    apart as the interpolation treats them (a body that slides and spins about its origin keeps
    doing so), t(s) = t_e + v·s and R(s) = exp(ω·s)·R_e; v and ω are measured between the end sample
    and the sample ``baseline`` seconds (at least one sample) inside it, so one noisy pose does not
    set the speed. Across a longer gap: with samples about a baseline inside both ends the rotation is
    both ends' carried on at their own angular velocities into the gap and blended by the time fraction
    (exact for a constant spin; SLERP alone takes the short way round, wrong once the body turns more
    than half a turn in the gap), else SLERP; the position is the cubic through both ends' positions
    and velocities (:func:`hermite`: exact for a constant slide and for a constant acceleration, so a
    body that stops and turns back unseen is followed; blending the carried positions was 27 cm off
    one that turned back in a 0.9 s gap, the cubic 2.7 cm), an end's velocity from a short run of
    samples when that is all there is (:func:`_end_partners`), the straight line's where there is
    none. With one sample the pose is held.

    ``pivot``: the body point whose path is interpolated and continued (the rotation turns the body
    about it); None: the origin. A body's motion is simplest about its centre: a box turning in place
    about its own axis, interpolated about a point 10 cm off that axis over a 1.7 s gap, was placed
    up to 9.7 cm off (the point's arc taken for its chord).

    Args:
        times: (N,) increasing sample times; poses: (N, 4, 4); pivot: (3,) in body coordinates.
    """
    times = np.asarray(times, dtype=np.float64)
    poses = torch.as_tensor(poses, dtype=torch.float64)
    if pivot is not None:  # the same rules for the frame at the pivot, then back to the origin
        shift = torch.eye(4, dtype=torch.float64)
        shift[:3, 3] = torch.as_tensor(pivot, dtype=torch.float64)
        back = shift.clone()
        back[:3, 3] = -shift[:3, 3]
        return pose_on_track(times, poses @ shift, t, baseline) @ back
    n, t = len(times), float(t)
    if n == 0:
        raise ValueError("a trajectory needs at least one pose")
    if n == 1:
        return poses[0].clone()
    if not times[0] - TIME_TOLERANCE_S <= t <= times[-1] + TIME_TOLERANCE_S:
        end = n - 1 if t > times[-1] else 0
        return _carried(times, poses, end, _velocity(times, poses, end, _baseline_partner(times, end, baseline, -1 if end else +1)), t)
    b = int(np.clip(np.searchsorted(times, t), 1, n - 1))
    a = b - 1
    span = times[b] - times[a]
    if span <= baseline or min(t - times[a], times[b] - t) <= TIME_TOLERANCE_S:  # no gap: SLERP + linear
        return interpolate_poses(times, poses, np.asarray([float(np.clip(t, times[0], times[-1]))]), tolerance=TIME_TOLERANCE_S)[0][0]
    (spin_a, moved_a), (spin_b, moved_b) = _end_partners(times, a, baseline, -1), _end_partners(times, b, baseline, +1)
    chord = (poses[b, :3, 3] - poses[a, :3, 3]) / span  # an end without a velocity follows the line
    vel_a = (None, chord) if moved_a is None else _velocity(times, poses, a, moved_a)
    vel_b = (None, chord) if moved_b is None else _velocity(times, poses, b, moved_b)
    s = (t - times[a]) / span
    if spin_a is not None and spin_b is not None:  # each end carried on at its own spin, blended
        out = interpolate_poses(np.array([0.0, 1.0]), torch.stack([_carried(times, poses, a, vel_a, t), _carried(times, poses, b, vel_b, t)]),
                                np.asarray([s]))[0][0]
    else:  # SLERP between the ends
        out = interpolate_poses(times[a:b + 1], poses[a:b + 1], np.asarray([float(t)]), tolerance=TIME_TOLERANCE_S)[0][0]
    out[:3, 3] = hermite(poses[a, :3, 3], vel_a[1], poses[b, :3, 3], vel_b[1], span, s)
    return out
