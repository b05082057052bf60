"""RGB-D image pyramids for dense odometry: intensity, gradients, edge-aware depth, vertices, normals.

Level l is the image downsampled 2^l times by 2x2 blocks, so a coarse pixel u covers fine pixels 2u and
2u + 1 and its camera matrix is :func:`downsample_K`. Depth is downsampled without averaging invalid
pixels or across depth edges; dynamic (masked) pixels are removed before any downsampling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from data_modules.sensor import KINECT_SIGMA, kinect_depth_sigma

Coeffs = tuple[float, float, float]


@dataclass(frozen=True, eq=False)
class PyramidLevel:
    """One RGB-D pyramid level, H x W pixels.

    K (3, 3); intensity (H, W) in [0, 1]; depth (H, W) metres, 0 = invalid or dynamic; usable (H, W)
    bool = depth in range and not dynamic; depth_sigma: the (a, b, z0) of the depth noise that sets
    where a normal crosses a depth edge. What only a reference is read for is built at its first
    read, once (a frame tracked against a reference never needs it: ~17 of 22 ms at 640x480, 4 levels):
    warp_image (1, 3, H, W) = [I, ∂I/∂u, ∂I/∂v] for bilinear sampling, geometry (7, H, W) = [depth,
    vertex (3), unit normal facing the camera (3), zero where undefined], packed so one gather serves
    a correspondence. A tracked frame reads its sampled pixels' vertices and normals (:meth:`points`).
    """

    K: torch.Tensor
    intensity: torch.Tensor
    depth: torch.Tensor
    usable: torch.Tensor
    depth_sigma: Coeffs = KINECT_SIGMA
    _built: dict[str, torch.Tensor] = field(default_factory=dict, repr=False)

    @property
    def warp_image(self) -> torch.Tensor:
        if "warp_image" not in self._built:
            self._built["warp_image"] = torch.cat([self.intensity[None], image_gradients(self.intensity)])[None]
        return self._built["warp_image"]

    @property
    def geometry(self) -> torch.Tensor:
        if "geometry" not in self._built:
            vertices = self._vertex_map()
            normals = vertex_normals(vertices, self.usable, float(self.K[0, 0]), self.depth_sigma)
            self._built["geometry"] = torch.cat([self.depth[None], vertices, normals])
        return self._built["geometry"]

    @property
    def vertices(self) -> torch.Tensor:
        """(H, W, 3) camera-frame points."""
        return self.geometry[1:4].permute(1, 2, 0)

    @property
    def normals(self) -> torch.Tensor:
        """(H, W, 3) unit normals facing the camera, zero where undefined."""
        return self.geometry[4:7].permute(1, 2, 0)

    def points(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices (3, N) and normals (3, N) of the N ``pixels`` (H, W) bool, in row-major order: read
        from the geometry where it is built, else computed at those pixels and their four neighbours
        alone (the same values)."""
        if "geometry" in self._built:
            return self.geometry[1:4, pixels], self.geometry[4:7, pixels]
        h, w = self.depth.shape
        at = torch.nonzero(pixels.flatten()).squeeze(1)
        rows, cols = at // w, at % w
        depth, usable = F.pad(self.depth, (1, 1, 1, 1)).flatten(), F.pad(self.usable, (1, 1, 1, 1)).flatten()
        K, dtype = self.K, self.depth.dtype

        def vertex(dy: int, dx: int) -> tuple[torch.Tensor, torch.Tensor]:  # (3, N) and (N,) of the pixels (dy, dx) away
            padded = (rows + 1 + dy) * (w + 2) + cols + 1 + dx
            points = camera_points((cols + dx).to(dtype), (rows + dy).to(dtype), depth.index_select(0, padded), K)
            return points, usable.index_select(0, padded)

        centre, valid = vertex(0, 0)
        sides = [vertex(dy, dx) for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0))]
        normals = facing_normals(centre, valid, [v for v, _ in sides], [m for _, m in sides], float(K[0, 0]), self.depth_sigma)
        return centre, normals

    @property
    def is_built(self) -> bool:
        """Whether the warp image and the geometry are built."""
        return "warp_image" in self._built and "geometry" in self._built

    def _vertex_map(self) -> torch.Tensor:
        """(3, H, W) camera-frame points of the depth map."""
        h, w = self.depth.shape
        u = torch.arange(w, dtype=self.depth.dtype, device=self.depth.device)
        v = torch.arange(h, dtype=self.depth.dtype, device=self.depth.device)[:, None]
        return camera_points(u, v, self.depth, self.K)


def camera_points(u: torch.Tensor, v: torch.Tensor, z: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(3, ...) camera-frame points of pixel columns u and rows v (broadcasting to z's (...)) at depths z (...)."""
    return torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])


def _blocks(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """(H, W) -> four (H//2, W//2) strided views, the pixels of each 2x2 block (odd last row/column dropped)."""
    h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
    return x[0:h:2, 0:w:2], x[0:h:2, 1:w:2], x[1:h:2, 0:w:2], x[1:h:2, 1:w:2]


def downsample_intensity(img: torch.Tensor) -> torch.Tensor:
    """(H, W) -> (H//2, W//2), the mean of each 2x2 block (new pixel u sits at 2u + 0.5, see downsample_K)."""
    a, b, c, d = _blocks(img)
    return (a + b + c + d) * 0.25


def downsample_depth(depth: torch.Tensor, coeffs: Coeffs = KINECT_SIGMA, n_sigma: float = 3.0) -> torch.Tensor:
    """(H, W) -> (H//2, W//2): mean of the valid depths of each 2x2 block within n_sigma·σ(z) of its nearest one.

    Invalid (0) depths never enter the mean, and a block straddling a depth edge keeps the front surface
    instead of a depth between two surfaces that belongs to neither; 0 where the block has no depth.
    """
    blocks = _blocks(depth)
    zmin = torch.stack([torch.where(b > 0, b, torch.full_like(b, math.inf)) for b in blocks]).amin(0)
    limit = zmin + n_sigma * kinect_depth_sigma(zmin, coeffs)
    total, count = torch.zeros_like(zmin), torch.zeros_like(zmin)
    for b in blocks:
        keep = (b > 0) & (b <= limit)
        total, count = total + b * keep, count + keep
    return torch.where(count > 0, total / count.clamp_min(1), torch.zeros_like(zmin))


def filter_depth(depth: torch.Tensor, coeffs: Coeffs = KINECT_SIGMA, radius: int = 2, space_sigma: float = 2.0,
                 range_sigmas: float = 3.0) -> torch.Tensor:
    """(H, W) depth (metres, 0 = invalid) bilaterally filtered in inverse depth, as KinectFusion filters
    the depth it aligns (Newcombe et al. 2011), with a range scale from the noise model.

    A structured-light sensor's noise and quantisation steps are about uniform in inverse depth
    (σ(z)/z², :func:`kinect_depth_sigma`: 0.0016–0.0019 m⁻¹ over 1–3 m), so each pixel averages the
    inverse depths of its (2·radius + 1)² window, weighted by exp(−d²/2 space_sigma²) over the pixel
    distance d and by exp(−Δ²/2 s²) over their difference Δ from its own, s = range_sigmas · σ(z̃)/z̃²
    at the median depth z̃: the noise of one surface is smoothed, a step to another surface is kept.
    Invalid pixels stay 0 (their inverse depth, 0, is far outside every valid one's range).
    OpenCV's bilateral filter, on the CPU: 13 ms a 640x480 frame, a tenth of the same filter in torch ops.
    """
    valid = depth > 0
    if not bool(valid.any()):
        return depth
    z = depth[valid].median()
    scale = float(range_sigmas * kinect_depth_sigma(z, coeffs) / z**2)
    inv = torch.where(valid, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))
    out = cv2.bilateralFilter(inv.detach().cpu().numpy().astype(np.float32), 2 * radius + 1, scale, space_sigma)
    out = torch.from_numpy(out).to(depth.device, depth.dtype)
    return torch.where(valid & (out > 0), 1.0 / out.clamp_min(1e-6), torch.zeros_like(depth))


def downsample_mask(mask: torch.Tensor) -> torch.Tensor:
    """(H, W) bool -> (H//2, W//2): dynamic where any pixel of the 2x2 block is."""
    a, b, c, d = _blocks(mask)
    return a | b | c | d


def downsample_K(K: torch.Tensor) -> torch.Tensor:
    """(3, 3) camera matrix of the 2x2-block-downsampled image: f/2, c' = (c + 0.5)/2 − 0.5."""
    Kd = K.clone()
    Kd[:2, :2] = K[:2, :2] / 2
    Kd[:2, 2] = (K[:2, 2] + 0.5) / 2 - 0.5
    return Kd


def image_gradients(img: torch.Tensor) -> torch.Tensor:
    """(H, W) -> (2, H, W) Scharr derivatives (∂/∂u, ∂/∂v) per pixel (kernel [3, 10, 3] ⊗ [−1, 0, 1] / 32)."""
    x = F.pad(img[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    du = x[:, 2:] - x[:, :-2]  # (H + 2, W)
    dv = x[2:] - x[:-2]  # (H, W + 2)
    gu = (3 * du[:-2] + 10 * du[1:-1] + 3 * du[2:]) / 32
    gv = (3 * dv[:, :-2] + 10 * dv[:, 1:-1] + 3 * dv[:, 2:]) / 32
    return torch.stack([gu, gv])


def pick_pixels(level: PyramidLevel, usable: torch.Tensor, stride: int, how: str = "grid") -> torch.Tensor:
    """(H, W) bool: at most one of the ``usable`` (H, W) pixels of ``level`` in each ``stride`` x ``stride`` tile.

    "grid": the tile's top-left pixel. "gradient": the tile's usable pixel of the largest intensity
    gradient, DSO's selection in its simplest form: as many pixels as the grid, spread as evenly, each
    where the photometric term learns the most about the motion (such pixels lie on colour edges, often
    depth edges too, so the point-to-plane term sees more boundary pixels). The gradients are the level's
    warp image, which the frame reuses if it becomes a reference.
    """
    if how == "grid" or stride <= 1:
        grid = torch.zeros_like(usable)
        grid[::stride, ::stride] = True
        return usable & grid
    g = level.warp_image[0, 1:]
    score = torch.where(usable, (g * g).sum(0), torch.full_like(level.intensity, -1.0))
    h, w = score.shape
    padded = F.pad(score[None, None], (0, -w % stride, 0, -h % stride), value=-1.0)
    best, index = F.max_pool2d(padded, stride, stride, return_indices=True)
    index = index.flatten()[best.flatten() >= 0]  # tiles without a usable pixel give none
    picked = torch.zeros_like(usable)
    picked[index // padded.shape[-1], index % padded.shape[-1]] = True
    return picked


def max_depth_jump(z: torch.Tensor, f: float, coeffs: Coeffs = KINECT_SIGMA) -> torch.Tensor:
    """Largest depth step (...) between neighbouring pixels on one surface at depth z (...).

    3 σ_pair of sensor noise plus the step of a surface seen 75° off the viewing ray, z/f · tan 75°.
    """
    return 3.0 * math.sqrt(2.0) * kinect_depth_sigma(z, coeffs) + z / f * 3.73


def vertex_normals(vertices: torch.Tensor, valid: torch.Tensor, f: float, coeffs: Coeffs = KINECT_SIGMA) -> torch.Tensor:
    """Unit normals (3, H, W) facing the camera from central differences of a vertex map (3, H, W).

    Zero where a 4-neighbour is invalid (``valid`` (H, W) bool) or lies across a depth discontinuity.
    """
    v = F.pad(vertices, (1, 1, 1, 1))
    m = F.pad(valid, (1, 1, 1, 1))
    h, w = valid.shape
    steps = ((0, 1), (0, -1), (1, 0), (-1, 0))  # right, left, down, up
    sides = [v[:, 1 + dy : h + 1 + dy, 1 + dx : w + 1 + dx] for dy, dx in steps]
    sides_valid = [m[1 + dy : h + 1 + dy, 1 + dx : w + 1 + dx] for dy, dx in steps]
    return facing_normals(vertices, valid, sides, sides_valid, f, coeffs)


def facing_normals(
    centre: torch.Tensor, valid: torch.Tensor, sides: list[torch.Tensor], sides_valid: list[torch.Tensor], f: float, coeffs: Coeffs
) -> torch.Tensor:
    """Unit normals (3, ...) facing the camera of points centre (3, ...) from the central differences
    of their right, left, down and up neighbours ``sides`` (4 x (3, ...)); zero where a point or a
    neighbour is not valid (bool (...) each) or a neighbour lies across a depth discontinuity."""
    right, left, down, up = sides
    dx, dy = right - left, down - up
    z = centre[2]
    jump = max_depth_jump(z, f, coeffs)
    ok = valid
    for side, side_valid in zip(sides, sides_valid):
        ok = ok & side_valid & ((side[2] - z).abs() <= jump)
    n = torch.stack([dx[1] * dy[2] - dx[2] * dy[1], dx[2] * dy[0] - dx[0] * dy[2], dx[0] * dy[1] - dx[1] * dy[0]])
    # 1/|n| with the sign that makes n face the camera; 0 where undefined (norm(dim=0) is slow on CPU).
    inv = torch.rsqrt((n * n).sum(0).clamp_min(1e-24))
    inv = torch.where((n * centre).sum(0) > 0, -inv, inv)
    return n * torch.where(ok, inv, torch.zeros_like(inv))


def _level(
    K: torch.Tensor, intensity: torch.Tensor, depth: torch.Tensor, dynamic: torch.Tensor, depth_range: tuple[float, float], coeffs: Coeffs
) -> PyramidLevel:
    """One pyramid level from its K (3, 3), intensity, depth and dynamic mask (H, W)."""
    usable = (depth >= depth_range[0]) & (depth <= depth_range[1]) & ~dynamic
    return PyramidLevel(K, intensity, torch.where(usable, depth, torch.zeros_like(depth)), usable, coeffs)


def build_pyramid(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    K: torch.Tensor,
    levels: int = 3,
    mask: torch.Tensor | None = None,
    depth_range: tuple[float, float] = (0.2, 6.0),
    depth_sigma: Coeffs = KINECT_SIGMA,
    smooth: bool = False,
) -> list[PyramidLevel]:
    """RGB-D image pyramid, finest first.

    Args:
        rgb: (H, W, 3) in [0, 1]. depth: (H, W) metres, 0 = invalid. K: (3, 3).
        levels: number of levels. mask: (H, W) bool, True = dynamic (excluded), or None.
        depth_range: usable (min, max) depth in metres. depth_sigma: (a, b, z0) of :func:`kinect_depth_sigma`.
        smooth: depth through :func:`filter_depth` first (after the dynamic pixels are removed).
    Returns:
        ``levels`` levels; level l is (H / 2^l, W / 2^l) with K scaled by :func:`downsample_K`.
    """
    K = K.to(device=depth.device, dtype=depth.dtype)
    intensity = rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114
    dynamic = torch.zeros_like(depth, dtype=torch.bool) if mask is None else mask.to(depth.device, torch.bool)
    depth = torch.where(dynamic, torch.zeros_like(depth), depth)  # dynamic depth must not leak into coarser levels
    if smooth:
        depth = filter_depth(depth, depth_sigma)
    out = [_level(K, intensity, depth, dynamic, depth_range, depth_sigma)]
    for _ in range(1, levels):
        K = downsample_K(K)
        intensity = downsample_intensity(intensity)
        depth = downsample_depth(depth, depth_sigma)
        dynamic = downsample_mask(dynamic)
        out.append(_level(K, intensity, depth, dynamic, depth_range, depth_sigma))
    return out


def crop_pyramid(levels: list[PyramidLevel], keep: torch.Tensor, margin: int = 4) -> list[PyramidLevel]:
    """The pyramid cut to the box around the finest level's ``keep`` (H, W) bool pixels plus ``margin``
    pixels, each level's K moved by its offset (the same pixels, camera rays and values: a view of
    one object stored as a reference holds its box, not the whole image). The box corners are
    multiples of 2^(levels-1), so coarse pixel u still covers fine pixels 2u, 2u + 1. Unchanged
    when ``keep`` is empty."""
    rows, cols = torch.nonzero(keep.any(1)).flatten(), torch.nonzero(keep.any(0)).flatten()
    if not len(rows):
        return levels
    step = 2 ** (len(levels) - 1)
    h, w = keep.shape
    y0, x0 = max(0, int(rows[0]) - margin) // step * step, max(0, int(cols[0]) - margin) // step * step
    y1, x1 = min(h, -(-(int(rows[-1]) + 1 + margin) // step) * step), min(w, -(-(int(cols[-1]) + 1 + margin) // step) * step)
    out = []
    for i, lv in enumerate(levels):
        a, b, c, d = y0 >> i, y1 >> i, x0 >> i, x1 >> i
        K = lv.K.clone()
        K[0, 2] -= c
        K[1, 2] -= a
        # the built parts cut from the whole level (normals at the box's edge see pixels outside it)
        built = {"warp_image": lv.warp_image[..., a:b, c:d].clone(), "geometry": lv.geometry[:, a:b, c:d].clone()}
        out.append(PyramidLevel(K, lv.intensity[a:b, c:d].clone(), lv.depth[a:b, c:d].clone(), lv.usable[a:b, c:d].clone(),
                                lv.depth_sigma, built))
    return out
