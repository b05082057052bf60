"""Dense RGB-D odometry: coarse-to-fine Gauss–Newton on SE(3) over photometric and point-to-plane residuals.

Pose convention: the estimate ``T_ref_cur`` (4, 4) maps points from the current camera frame into the
reference camera frame, so ``c2w_cur = c2w_ref @ T_ref_cur``. Every iteration warps the current frame's
pixels that have depth into the reference image (projective data association, p' = T p) and stacks

* photometric residuals  r_I = I_ref(π(p')) − I_cur(u) [− b, a robust global brightness offset],
* point-to-plane residuals r_G = n_ref · (p' − v_ref) at the nearest reference pixel,

each divided by its own noise scale, so their relative weight is set by the data, not by a constant:
r_I by s_I = 1.4826·MAD(r_I) (at least one 8-bit step), r_G by σ_pair(z)·s_G where σ(z) is the
Kinect v1 axial noise model (it shapes the per-pixel weights) and s_G the MAD of r_G/σ_pair. IRLS
weights (Huber or Cauchy) act on the normalised residuals; the 6x6 normal equations are summed in
float64 and the update is applied on the left, T ← exp(δ) T, δ = (v, w) as :func:`tivne.geometry.se3_exp`.

After Steinbrücker et al. (2011), Kerl et al. (DVO, 2013; rolling shutter: Kerl et al., ICCV 2015), ElasticFusion (2015),
Open3D's hybrid odometry; σ(z) = 0.0012 + 0.0019 (z − 0.4)² m from Nguyen, Izadi, Lovell (3DIMPVT 2012).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from data_modules.poses import rotation_vector
from data_modules.sensor import kinect_depth_sigma
from tivne.config import OdometryConfig
from tivne.geometry import adjoint_vw, eigen_range, invert_pose, pixel_coordinates, se3_step
from tivne.slam.tracking.pyramid import PyramidLevel, build_pyramid, pick_pixels
from tivne.slam.tracking.robust import cauchy_weights, huber_weights, normal_equations, robust_scale, solve_damped, subsample
from tivne.slam.tracking.sensor import Shutter, parallax_pixels


@dataclass(frozen=True)
class OdometryResult:
    """Outcome of :func:`track_pyramids`. Statistics are at the last linearisation of the finest level.

    T_ref_cur: (4, 4) float64, ``c2w_cur = c2w_ref @ T_ref_cur``. converged: the finest level's update
    fell below the tolerances. num_valid: correspondences that entered the last step. overlap: usable
    pairs (current pixel with depth landing on a usable reference pixel) / current pixels with depth.
    inlier_ratio: inliers / usable pairs (depth difference within ``inlier_sigmas`` σ_pair). rms_photometric
    [intensity], rms_geometric [m]: IRLS-weighted RMS of each term (nan when the term is off).
    iterations: per level, coarsest first. min_eigenvalue, condition: of the final 6x6 information matrix
    (twist units m, rad); pose_std: 1/sqrt(min_eigenvalue), the σ along the worst-determined twist
    direction (optimistic: pixels are treated as independent). ok: all thresholds of the config met.
    information: (6, 6) float64 JᵀWJ of the finest level's last linearisation, for the twist
    δ = (v, w) (metres, radians) of a left perturbation T_ref_cur ← exp(δ) T_ref_cur (the update of
    :func:`track_pyramids`); the pose graph converts it to its own tangent (:mod:`tivne.slam.backend`).
    """

    T_ref_cur: torch.Tensor
    converged: bool
    num_valid: int
    overlap: float
    inlier_ratio: float
    rms_photometric: float
    rms_geometric: float
    iterations: tuple[int, ...]
    min_eigenvalue: float
    condition: float
    pose_std: float
    ok: bool
    information: torch.Tensor


@dataclass(frozen=True)
class PosePrior:
    """A Gaussian prior on T_ref_cur: the pose ``T`` (4, 4) float64 it pulls towards and its
    ``information`` (6, 6) float64 in the odometry's tangent (the left twist δ = (v, w) of
    T_ref_cur ← exp(δ) T_ref_cur). Where the pixels constrain a direction well the prior hardly
    moves it; where they do not (a symmetric object's spin, a blurred texture) the prior decides."""

    T: torch.Tensor
    information: torch.Tensor

    def residual(self, T: torch.Tensor) -> torch.Tensor:
        """(6,) float64 e = (t, ω) of T · T_prior⁻¹ (first order in the deviation, as the GN step)."""
        D = T.double() @ invert_pose(self.T.double())
        return torch.cat([D[:3, 3], rotation_vector(D[:3, :3])])


@dataclass(frozen=True)
class _Source:
    """The current frame's pixels at one level, in its colour camera's frame at the colour timestamp:
    points (3, N), intensity (N,), normals (3, N), has_colour (N,) bool (the point sees the colour image), depth_noise (N,)
    σ(z) of their depths, parallax (N,) pixels its colour may be off (:func:`parallax_pixels`; None: registered colour),
    terms: the columns the (photometric, point-to-plane) terms read (all of them unless a "split" pick thinned the level)."""

    points: torch.Tensor
    intensity: torch.Tensor
    normals: torch.Tensor
    has_colour: torch.Tensor
    depth_noise: torch.Tensor
    parallax: torch.Tensor | None = None
    terms: tuple[slice, slice] = (slice(None), slice(None))

    def columns(self, which: slice) -> "_Source":
        """The same source restricted to the columns ``which`` (views, no copies)."""
        if which == slice(None):  # every pick but split: each term reads every column
            return self
        parallax = None if self.parallax is None else self.parallax[which]
        return _Source(self.points[:, which], self.intensity[which], self.normals[:, which], self.has_colour[which],
                       self.depth_noise[which], parallax)


def _sample(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear samples (C, N) of image (1, C, H, W) at pixel coordinates u, v (N,) (zeros outside)."""
    h, w = image.shape[-2:]
    grid = torch.stack([u * (2.0 / (w - 1)) - 1, v * (2.0 / (h - 1)) - 1], -1)
    return F.grid_sample(image, grid[None, None], mode="bilinear", align_corners=True)[0, :, 0]


def _project(p: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel columns u, rows v and depths z (N,) of points p (3, N)."""
    return *pixel_coordinates(p[0], p[1], p[2], K), p[2]


def _in_image(u: torch.Tensor, v: torch.Tensor, z: torch.Tensor, shape: tuple[int, ...], min_depth: float) -> torch.Tensor:
    """(N,) bool: in front of the camera and a pixel or more inside the border (gradients there are padding)."""
    h, w = shape
    return (z > min_depth) & (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)


def _source(level: PyramidLevel, max_points: float, T_rgb_depth: torch.Tensor | None, cfg: OdometryConfig,
            shutter: Shutter | None) -> _Source:
    sel = level.usable
    stride = math.ceil(math.sqrt(int(sel.sum()) / max(max_points, 1.0))) if max_points > 0 else 1
    terms = (slice(None), slice(None))
    if cfg.pick == "split" and stride > 1:  # the photometric term on strong gradients, point-to-plane on the even grid
        grid, strong = pick_pixels(level, sel, stride, "grid"), pick_pixels(level, sel, stride, "gradient")
        parts = (strong & ~grid, strong & grid, grid & ~strong)  # ordered so that each term reads one slice
        first, both = int(parts[0].sum()), int(parts[1].sum())
        terms, sel = (slice(0, first + both), slice(first, None)), grid | strong
        points, normals = (torch.cat(x, 1) for x in zip(*(level.points(m) for m in parts)))
        intensity = torch.cat([level.intensity[m] for m in parts])
    else:
        sel = pick_pixels(level, sel, stride, cfg.pick) if stride > 1 else sel
        (points, normals), intensity = level.points(sel), level.intensity[sel]
    if T_rgb_depth is None:
        has_colour = torch.ones_like(intensity, dtype=torch.bool)
    else:  # depth taken at another time than colour: move the points to the colour time, read their colour there
        R, t = T_rgb_depth[:3, :3].to(points), T_rgb_depth[:3, 3].to(points)
        points, normals = R @ points + t[:, None], R @ normals
        u, v, z = _project(points, level.K)
        intensity, has_colour = _sample(level.intensity[None, None], u, v)[0], _in_image(u, v, z, sel.shape, cfg.min_depth)
    if shutter is not None:  # each row seen at its own time: the points where the middle row's camera has them
        v = _project(points, level.K)[1]
        points = points + shutter.motion(points, shutter.row_times(v, sel.shape[0]))
    return _Source(points, intensity, normals, has_colour, kinect_depth_sigma(points[2], cfg.depth_sigma), terms=terms)


@dataclass(frozen=True)
class _Linearisation:
    """Normal equations H (6, 6), g (6,) float64 at one pose, its correspondences, the robust scales used (photometric,
    geometric); :func:`_result`'s statistics from usable, inliers (N,) bool and each term's (residuals, IRLS weights) or None."""

    H: torch.Tensor
    g: torch.Tensor
    num_valid: int
    scales: tuple[torch.Tensor | None, torch.Tensor | None]
    usable: torch.Tensor
    inliers: torch.Tensor
    terms: tuple[tuple[torch.Tensor, torch.Tensor] | None, tuple[torch.Tensor, torch.Tensor] | None]


def _kernel(e: torch.Tensor, cfg: OdometryConfig) -> torch.Tensor:
    return huber_weights(e) if cfg.robust == "huber" else cauchy_weights(e)


def _weighted_rms(r: torch.Tensor, w: torch.Tensor) -> float:
    total = float(w.sum())
    return float(((w * r * r).sum() / total).sqrt()) if total > 0 else math.nan


def _rows(p: torch.Tensor, g: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """(7, N) = [g, p × g, r]: Jacobian rows of a residual whose gradient w.r.t. the point p (3, N) is g (3, N).

    With the left update p ← p + v + w × p, dr/d(v, w) = [gᵀ, (p × g)ᵀ].
    """
    x, y, z = p
    return torch.stack([g[0], g[1], g[2], y * g[2] - z * g[1], z * g[0] - x * g[2], x * g[1] - y * g[0], r])


def brightness_gain(ref: torch.Tensor, cur: torch.Tensor, valid: torch.Tensor, limit: float = 2.0) -> torch.Tensor:
    """Robust contrast ratio a (a scalar in [1/limit, limit]) of the reference intensities ref (N,)
    to the current ones cur (N,) at the valid (N,) pairs: MAD(ref) / MAD(cur), the gain of an affine
    brightness change I_ref = a·I_cur + b (the bias is the median offset that follows)."""
    a, b = subsample(ref, valid), subsample(cur, valid)
    mad = lambda x: (x - x.median()).abs().median()  # noqa: E731
    return (mad(a) / mad(b).clamp_min(1e-6)).clamp(1.0 / limit, limit)


def _photometric(
    ref: PyramidLevel, src: _Source, p: torch.Tensor, uv: tuple[torch.Tensor, torch.Tensor], dp_dz: torch.Tensor, valid: torch.Tensor,
    cfg: OdometryConfig, given: torch.Tensor | None = None,
):
    """Rows (7, N) of :func:`_rows`, normalised weights (N,) (0 where not valid), IRLS weights (N,) and
    the robust scale of the residuals (``given``: that one instead of the residuals' own).

    p (3, N) warped points, uv their pixel columns and rows (N,), dp_dz (3, N) their motion per metre of current depth.
    The gradient of I_ref(π(p)) w.r.t. p is g = ∇I·∂π/∂p = (I_u f_x, I_v f_y, −(I_u f_x x + I_v f_y y)/z) / z.
    With ``photometric_depth_noise`` each residual's σ² = s² + (g · ∂p/∂z_cur)² σ(z_cur)²: the current
    depth's noise moves the warped pixel, which matters where the reference image has strong gradients.
    """
    s = _sample(ref.warp_image, *uv)  # (3, N): I, ∂I/∂u, ∂I/∂v
    valid = valid & src.has_colour
    r = s[0] - src.intensity
    if cfg.brightness_gain and bool(valid.any()):  # an exposure change scales contrast too: I_ref ≈ a·I_cur + b
        r = s[0] - brightness_gain(s[0], src.intensity, valid) * src.intensity
    if cfg.brightness_offset and bool(valid.any()):
        r = r - subsample(r, valid).median()
    x, y, z = p
    gu, gv = s[1] * (ref.K[0, 0] / z), s[2] * (ref.K[1, 1] / z)
    g = torch.stack([gu, gv, -(gu * x + gv * y) / z])
    noise = robust_scale(r, cfg.intensity_sigma_min, valid) if given is None else given
    scale = noise
    if cfg.photometric_depth_noise:  # per pixel: the current depth's noise seen through the gradient
        scale = torch.hypot(noise, (g * dp_dz).sum(0) * src.depth_noise)
    if src.parallax is not None:  # per pixel: where unregistered colour may sit, seen through the gradient
        scale = torch.hypot(scale, src.parallax * torch.hypot(s[1], s[2]))
    rows = _rows(p, g, r)
    wts = _kernel(r / scale, cfg) * valid
    return rows, wts / scale**2, wts, noise


def _geometric(
    n_cur: torch.Tensor, p: torch.Tensor, pd: torch.Tensor, geo: torch.Tensor, valid: torch.Tensor, sigma: torch.Tensor,
    RA: torch.Tensor | None, cfg: OdometryConfig, given: torch.Tensor | None = None,
):
    """Point-to-plane rows, weights and the scale factor on σ(z) as :func:`_photometric`.

    p (3, N): points in the reference colour frame (the one T_ref_cur maps to), pd = RA p + tA the same in
    the reference depth frame, n_cur (3, N) the current normals rotated into it, geo (7, N) the reference
    pixel's geometry. r = n · (pd − v_ref), gradient RAᵀ n w.r.t. p; pairs with undefined or disagreeing
    normals get weight 0.
    """
    n = geo[4:7]
    agree = valid & ((n * n_cur).sum(0) >= math.cos(math.radians(cfg.max_normal_angle_deg)))
    r = (n * (pd - geo[1:4])).sum(0)
    factor = robust_scale(r / sigma, 0.0 if cfg.geometric_scale == "data" else 1.0, agree) if given is None else given
    if cfg.geometric_scale == "data":  # σ(z) shapes the per-pixel weights, the residuals set the overall scale
        scale = (factor * sigma).clamp_min(cfg.depth_quantum)
    else:  # ≥ σ: never trusted beyond the sensor model
        scale = factor * sigma
    wts = _kernel(r / scale, cfg) * agree
    return _rows(p, n if RA is None else RA.T @ n, r), wts / scale**2, wts, factor


def _linearise(
    ref: PyramidLevel, src: _Source, T: torch.Tensor, A: torch.Tensor | None, cfg: OdometryConfig,
    scales: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None), shutter: Shutter | None = None,
) -> _Linearisation:
    """Warp the current points by T (4, 4) into the reference and build the robust normal equations.

    A (4, 4) or None: reference colour frame -> reference depth frame (inverse of its T_rgb_depth).
    scales: the robust scales (photometric, geometric) to use instead of the residuals' own (None).
    Fixed-size (3, N) arrays with zero weights rather than boolean compaction: on CPU a gather is cheap,
    a compaction of every array is not.
    """
    R, t = T[:3, :3].to(src.points.dtype), T[:3, 3].to(src.points.dtype)
    p = R @ src.points + t[:, None]
    if shutter is not None:  # the reference's row that sees p was read while its camera moved: p as that camera has it
        p = p - shutter.motion(p, shutter.row_times(_project(p, ref.K)[1], ref.intensity.shape[0]))
    u, v, z = _project(p, ref.K)
    RA, pd, ud, vd, zd = None, p, u, v, z
    h, w = ref.intensity.shape
    inside = _in_image(u, v, z, (h, w), cfg.min_depth)
    if A is not None:
        RA = A[:3, :3].to(p.dtype)
        pd = RA @ p + A[:3, 3].to(p.dtype)[:, None]
        ud, vd, zd = _project(pd, ref.K)
        inside = inside & _in_image(ud, vd, zd, (h, w), cfg.min_depth)
    idx = vd.round().long().clamp(0, h - 1) * w + ud.round().long().clamp(0, w - 1)
    geo = ref.geometry.view(7, -1).index_select(1, idx)  # nearest reference pixel (projective association)
    usable = inside & (geo[0] > 0)
    sigma = torch.hypot(kinect_depth_sigma(zd, cfg.depth_sigma), kinect_depth_sigma(geo[0], cfg.depth_sigma))
    dz = ((zd - geo[0]) / sigma).abs()
    valid = usable & (dz <= cfg.outlier_sigmas * robust_scale(dz, 1.0, usable))
    H, g = torch.zeros(6, 6, dtype=torch.float64, device=p.device), torch.zeros(6, dtype=torch.float64, device=p.device)
    terms, used = [None, None], [None, None]
    if cfg.photometric:
        c = src.terms[0]
        dp_dz = (p[:, c] - t[:, None]) / src.points[2, c]  # the current point moves along its ray with its depth
        rows, w_norm, rms_w, used[0] = _photometric(ref, src.columns(c), p[:, c], (u[c], v[c]), dp_dz, valid[c], cfg, scales[0])
        H, g = normal_equations(rows, w_norm * cfg.photometric_weight)
        terms[0] = (rows[6], rms_w)
    if cfg.geometric:
        c = src.terms[1]
        n_cur = (R if RA is None else RA @ R) @ src.normals[:, c]
        rows, w_norm, rms_w, used[1] = _geometric(n_cur, p[:, c], pd[:, c], geo[:, c], valid[c], sigma[c], RA, cfg, scales[1])
        Hk, gk = normal_equations(rows, w_norm)
        H, g, terms[1] = H + Hk, g + gk, (rows[6], rms_w)
    return _Linearisation(H, g, int(valid.sum()), (used[0], used[1]), usable, usable & (dz <= cfg.inlier_sigmas), (terms[0], terms[1]))


def _track_level(ref: PyramidLevel, src: _Source, T: torch.Tensor, A: torch.Tensor | None, cfg: OdometryConfig,
                 prior: PosePrior | None, also: tuple[tuple[PyramidLevel, torch.Tensor], ...], shutters: tuple[Shutter | None, ...]):
    """Gauss–Newton iterations at one level -> (T, iterations, converged, last linearisation of ``ref``).

    ``also``: more reference levels with their (4, 4) T_other_ref, whose normal equations join
    ``ref``'s: T_other_cur = T_other_ref · T, so a step exp(δ) · T is exp(Ad δ) · T_other_cur there
    (Ad the adjoint of T_other_ref) and their H, g enter as Adᵀ H Ad, Adᵀ g. They are weighted with
    ``ref``'s robust scales: each view's own would make the joint pose follow whichever view fits it
    best (its scale shrinks, its weight grows) instead of averaging them. ``shutters``: ref's, then each view's.
    Converged: the update moves the image by < tol_pixels, or by < stall_pixels without shrinking to
    half the previous one (a limit cycle of the discrete projective association and the reweighting).
    """
    f = float(ref.K[0, 0])
    z_mid = float(src.points[2].median()) if src.points.shape[1] else 1.0
    last = math.inf
    adjoints = [adjoint_vw(T_other_ref.to(T)) for _, T_other_ref in also]
    shutters = tuple(shutters) + (None,) * (1 + len(also) - len(shutters))  # a global shutter where none is given
    for it in range(cfg.max_iterations):
        lin = _linearise(ref, src, T, A, cfg, shutter=shutters[0])
        if lin.num_valid < cfg.min_correspondences:
            return T, it, False, lin
        H, g = lin.H, lin.g
        for (other, T_other_ref), Ad, shutter in zip(also, adjoints, shutters[1:]):
            more = _linearise(other, src, T_other_ref.to(T) @ T, None, cfg, lin.scales, shutter)  # one noise scale for all views
            if more.num_valid >= cfg.min_correspondences:
                H, g = H + Ad.T @ more.H.to(H) @ Ad, g + Ad.T @ more.g.to(g)
        if prior is not None:  # ½ eᵀ Λ e with e ≈ e0 + δ
            Lam = prior.information.to(H)
            H, g = H + Lam, g + Lam @ prior.residual(T).to(g)
        delta = solve_damped(H, g, cfg.damping)
        T = se3_step(delta) @ T
        step = (float(delta[3:].norm()) + float(delta[:3].norm()) / z_mid) * f
        if step < cfg.tol_pixels or (step < cfg.stall_pixels and step > 0.5 * last):
            return T, it + 1, True, lin
        last = step
    return T, cfg.max_iterations, False, lin


def track_pyramids(
    ref: list[PyramidLevel],
    cur: list[PyramidLevel],
    T_init: torch.Tensor | None = None,
    config: OdometryConfig = OdometryConfig(),
    ref_rgb_depth: torch.Tensor | None = None,
    cur_rgb_depth: torch.Tensor | None = None,
    prior: PosePrior | None = None,
    also: tuple[tuple[list[PyramidLevel], torch.Tensor], ...] = (),
    shutters: tuple[Shutter | None, ...] = (),
) -> OdometryResult:
    """Estimate T_ref_cur (``c2w_cur = c2w_ref @ T_ref_cur``, colour camera frames) coarse to fine.

    Args:
        ref, cur: pyramids from :func:`frame_pyramid` (same config, finest first).
        T_init: (4, 4) initial T_ref_cur, e.g. a constant-velocity prediction; identity if None.
        config: :class:`OdometryConfig`.
        ref_rgb_depth, cur_rgb_depth: (4, 4) T_rgb_depth of each frame, mapping its depth camera frame
            (at the depth timestamp) into its colour camera frame (at the colour timestamp), for sensors
            whose depth and colour are not simultaneous (e.g. exp(ξ·Δt) from a velocity); None = simultaneous.
        prior: an optional :class:`PosePrior` on T_ref_cur, added to every level's normal equations
            (the result's ``information`` stays the pixels' own).
        shutters: rolling shutters (:class:`Shutter`): the current frame's, then ``ref``'s, then one per
            ``also`` view (None where a view's is unknown); () = global shutter. The current frame's
            velocity follows the estimate at each level when it knows the previous frame (``previous``).
        also: more references of the same scene, each (pyramid, (4, 4) T_other_ref: ``ref``'s colour
            camera in its frame), aligned jointly with ``ref`` at the finest level (one pose, all their
            normal equations, ``ref``'s noise scales: their pixels average out each single view's
            noise; the coarser levels find the basin from ``ref`` alone); simultaneous depth and
            colour. The result's statistics and information are ``ref``'s alone.
    Returns:
        :class:`OdometryResult`; on failure (no overlap, no depth) ``ok`` is False, never a silent identity.
    """
    device = ref[0].depth.device
    T = torch.eye(4, dtype=torch.float64, device=device) if T_init is None else T_init.to(device, torch.float64)
    A = None if ref_rgb_depth is None else invert_pose(ref_rgb_depth.to(device, torch.float64))
    cur_rgb_depth = None if cur_rgb_depth is None else cur_rgb_depth.to(device, torch.float64)
    iterations, converged, lin, n_src = [], False, None, 0
    for level in reversed(range(min(len(ref), len(cur), config.levels))):
        shutter = shutters[0].at(T) if shutters else None  # the current frame's velocity as estimated so far
        src = _source(cur[level], config.max_points / config.coarse_points_ratio**level, cur_rgb_depth, config, shutter)
        if config.colour_parallax_m:  # once per level: the points do not move between iterations
            src = replace(src, parallax=parallax_pixels(src.points[2], float(cur[level].K[0, 0]), config.colour_parallax_m))
        views = tuple((p[level], X) for p, X in also) if level == 0 else ()
        T, its, converged, lin = _track_level(ref[level], src, T, A, config, prior, views, shutters[1:])
        iterations.append(its)
        n_src = src.points.shape[1]
    return _result(T, converged, lin, n_src, tuple(iterations), config)


def _result(
    T: torch.Tensor, converged: bool, lin: _Linearisation, n_src: int, iterations: tuple[int, ...], cfg: OdometryConfig
) -> OdometryResult:
    min_eig, max_eig = eigen_range(lin.H)
    pose_std = 1.0 / math.sqrt(min_eig) if min_eig > 0 else math.inf
    num_usable = int(lin.usable.sum())
    overlap = num_usable / max(n_src, 1)
    inlier_ratio = int(lin.inliers.sum()) / max(num_usable, 1)
    rms = [math.nan if term is None else _weighted_rms(*term) for term in lin.terms]
    ok = (
        converged
        and lin.num_valid >= cfg.min_correspondences
        and overlap >= cfg.min_overlap
        and inlier_ratio >= cfg.min_inlier_ratio
        and pose_std <= cfg.max_pose_std
    )
    return OdometryResult(
        T_ref_cur=T,
        converged=converged,
        num_valid=lin.num_valid,
        overlap=overlap,
        inlier_ratio=inlier_ratio,
        rms_photometric=rms[0],
        rms_geometric=rms[1],
        iterations=iterations,
        min_eigenvalue=min_eig,
        condition=max_eig / min_eig if min_eig > 0 else math.inf,
        pose_std=pose_std,
        ok=bool(ok),
        information=lin.H.detach().cpu(),
    )


def frame_pyramid(
    rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, config: OdometryConfig, mask: torch.Tensor | None = None
) -> list[PyramidLevel]:
    """:func:`tivne.slam.tracking.pyramid.build_pyramid` (same arguments) with the levels, depth range and noise of ``config``."""
    return build_pyramid(rgb, depth, K, config.levels, mask, (config.min_depth, config.max_depth), config.depth_sigma,
                         smooth=config.depth_filter)


def rgbd_odometry(
    ref_rgb: torch.Tensor,
    ref_depth: torch.Tensor,
    cur_rgb: torch.Tensor,
    cur_depth: torch.Tensor,
    K: torch.Tensor,
    T_init: torch.Tensor | None = None,
    ref_mask: torch.Tensor | None = None,
    cur_mask: torch.Tensor | None = None,
    config: OdometryConfig = OdometryConfig(),
) -> OdometryResult:
    """Relative pose of two RGB-D frames: builds both pyramids, then :func:`track_pyramids`.

    Args:
        ref_rgb, cur_rgb: (H, W, 3) in [0, 1]. ref_depth, cur_depth: (H, W) metres, 0 = invalid.
        K: (3, 3). T_init: (4, 4) initial T_ref_cur or None. ref_mask, cur_mask: (H, W) bool,
        True = dynamic (excluded), or None. config: :class:`OdometryConfig`.
    Returns:
        :class:`OdometryResult` with ``T_ref_cur`` such that ``c2w_cur = c2w_ref @ T_ref_cur``.
    """
    ref = frame_pyramid(ref_rgb, ref_depth, K, config, ref_mask)
    cur = frame_pyramid(cur_rgb, cur_depth, K, config, cur_mask)
    return track_pyramids(ref, cur, T_init, config)
