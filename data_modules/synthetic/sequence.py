"""The built-in synthetic sequence: a textured room, static objects and one moving cube.

Everything is generated procedurally and rendered *exactly* by vectorised analytic ray casting
(slab test for oriented boxes in each box's local frame, closed-form ray/sphere), so the dataset
comes with perfect ground truth: camera poses, dynamic masks, the moving object's pose and the
exact signed distance / surface of the scene at any time.

World frame ("room frame"): metres, z up, the room is the box
``[-2, 2] x [-1.5, 1.5] x [0, 2.6]``; the floor is ``z = 0``. Camera poses are camera-to-world with
OpenCV camera axes (x right, y down, z forward).

Colours are a pure function of the surface point in the owning primitive's local frame (hashed
multi-octave value noise through a per-surface palette, with a fixed half-Lambert shading term
evaluated in that local frame), so the same surface point has the same noise-free colour in every
frame -- also on the moving cube. The scene and the trajectories are fixed; ``seed`` only selects the
sensor-noise realisation (depth noise, depth holes, colour noise).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.sequence import SequenceDataset

__all__ = ["MovingCubeSequence"]

# Bump whenever the rendered images change, so stale caches are not reused.
RENDER_VERSION = 1

ROOM_MIN = (-2.0, -1.5, 0.0)
ROOM_MAX = (2.0, 1.5, 2.6)
CUBE_HALF = 0.18  # the moving cube has 0.36 m edges

_M32 = 0xFFFFFFFF
_PRIMES = (73856093, 19349663, 83492791)


# ----------------------------------------------------------------------------------------------
# Small pure helpers
# ----------------------------------------------------------------------------------------------


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _look_at(position: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(3, 3) camera-to-world rotation (OpenCV axes) of a camera at ``position`` looking at ``target``."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _hash_to_unit(h: torch.Tensor) -> torch.Tensor:
    """int64 tensor -> float32 in [0, 1): 32-bit avalanche hash (lowbias32) of the low 32 bits."""
    h = h & _M32
    h = ((h ^ (h >> 16)) * 0x7FEB352D) & _M32
    h = ((h ^ (h >> 15)) * 0x846CA68B) & _M32
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).to(torch.float32) * (1.0 / 16777216.0)


def value_noise(p: torch.Tensor, salt: int = 0) -> torch.Tensor:
    """Smooth hashed lattice value noise.

    Args:
        p: (N, 3) points (lattice spacing 1).
        salt: integer that selects an independent noise field.
    Returns:
        (N,) float32 in [0, 1], C1-continuous in ``p`` (smoothstep-weighted trilinear interpolation).
    """
    pf = torch.floor(p)
    f = (p - pf).to(torch.float32)
    w = f * f * (3.0 - 2.0 * f)
    i = pf.to(torch.int64)
    hx = [i[:, 0] * _PRIMES[0], (i[:, 0] + 1) * _PRIMES[0]]
    hy = [i[:, 1] * _PRIMES[1], (i[:, 1] + 1) * _PRIMES[1]]
    hz = [i[:, 2] * _PRIMES[2] ^ salt, (i[:, 2] + 1) * _PRIMES[2] ^ salt]
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    out = None
    for dz in (0, 1):
        plane = None
        for dy in (0, 1):
            hyz = hy[dy] ^ hz[dz]
            v0 = _hash_to_unit(hx[0] ^ hyz)
            v1 = _hash_to_unit(hx[1] ^ hyz)
            row = v0 + (v1 - v0) * wx
            plane = row if plane is None else plane + (row - plane) * wy
        out = plane if out is None else out + (plane - out) * wz
    return out


def fbm(p: torch.Tensor, salt: int = 0, octaves: int = 5) -> torch.Tensor:
    """Multi-octave value noise (fractal Brownian motion), (N, 3) metres -> (N,) roughly in [0, 1].

    Octave frequencies are incommensurate (about 2.3, 5.3, 12.2, 28, 64 per metre) and each octave is
    offset by an irrational shift, so the pattern does not repeat.
    """
    total = torch.zeros(p.shape[0], dtype=torch.float32, device=p.device)
    norm = 0.0
    freq, amp = 2.3, 1.0
    for k in range(octaves):
        shift = torch.tensor([0.37 * k, 0.61 * k, 0.13 * k], dtype=p.dtype, device=p.device)
        total = total + amp * value_noise(p * freq + shift, salt + 1013 * k)
        norm += amp
        freq *= 2.31
        amp *= 0.62
    return total / norm


def box_sdf(p_local: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """Exact signed distance of points (N, 3), given in the box's frame, to a box of ``half`` extents."""
    q = p_local.abs() - half
    outside = q.clamp_min(0).norm(dim=-1)
    inside = q.max(dim=-1).values.clamp_max(0)
    return outside + inside


# ----------------------------------------------------------------------------------------------
# Scene description
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Surface:
    """Texture parameters of one primitive: palette col = a + b cos(2 pi (c n + d))."""

    salt: int
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    c: tuple[float, float, float]
    d: tuple[float, float, float]


# Primitive ids (also the order of the hit candidates in the ray caster).
ROOM, BOX_A, BOX_B, SPHERE, CUBE = 0, 1, 2, 3, 4
PRIMITIVE_NAMES = ("room", "box_a", "box_b", "sphere", "cube")

# Surface id = 8 * primitive id + face; the room's six faces (face = 2 * axis + (normal > 0)) get
# their own palettes, the objects one palette each.
_SURFACES = {
    8 * ROOM + 0: _Surface(11, (0.62, 0.55, 0.48), (0.30, 0.28, 0.25), (1.3, 1.1, 0.9), (0.00, 0.12, 0.27)),
    8 * ROOM + 1: _Surface(13, (0.55, 0.58, 0.50), (0.28, 0.30, 0.26), (1.1, 1.3, 0.8), (0.45, 0.30, 0.10)),
    8 * ROOM + 2: _Surface(17, (0.60, 0.52, 0.55), (0.30, 0.25, 0.28), (0.9, 1.2, 1.4), (0.20, 0.55, 0.35)),
    8 * ROOM + 3: _Surface(19, (0.50, 0.56, 0.60), (0.26, 0.28, 0.30), (1.2, 0.9, 1.1), (0.70, 0.15, 0.45)),
    8 * ROOM + 4: _Surface(29, (0.52, 0.50, 0.47), (0.28, 0.27, 0.26), (1.0, 1.0, 1.3), (0.35, 0.60, 0.80)),
    8 * ROOM + 5: _Surface(31, (0.66, 0.64, 0.60), (0.22, 0.22, 0.24), (1.4, 1.2, 1.0), (0.05, 0.25, 0.50)),
    8 * BOX_A: _Surface(23, (0.45, 0.55, 0.40), (0.35, 0.30, 0.30), (1.0, 1.4, 1.1), (0.30, 0.20, 0.60)),
    8 * BOX_B: _Surface(37, (0.40, 0.45, 0.62), (0.30, 0.32, 0.35), (1.2, 0.8, 1.5), (0.55, 0.35, 0.10)),
    8 * SPHERE: _Surface(41, (0.58, 0.44, 0.56), (0.35, 0.30, 0.35), (0.9, 1.3, 1.0), (0.10, 0.70, 0.40)),
    8 * CUBE: _Surface(53, (0.70, 0.42, 0.22), (0.30, 0.35, 0.22), (1.6, 1.0, 1.3), (0.00, 0.33, 0.67)),
}
# Static objects: boxes standing on the floor (rotated about z), a sphere resting on the floor.
_BOX_A = (np.array([-1.05, 0.75, 0.25]), np.array([0.35, 0.25, 0.25]), _rot_z(math.radians(20.0)))
_BOX_B = (np.array([1.15, 0.85, 0.40]), np.array([0.20, 0.20, 0.40]), _rot_z(math.radians(-15.0)))
_SPHERE = (np.array([0.30, 1.05, 0.22]), 0.22)
# Light direction used for shading, expressed in each primitive's local frame.
_LIGHT = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])


class MovingCubeSequence(SequenceDataset):
    """Procedural, exactly rendered RGB-D sequence with one moving cube (the default dataset).

    Args:
        num_frames: number of frames (>= 1).
        fps: frame rate; frame ``i`` has timestamp ``i / fps`` seconds.
        width, height: image size in pixels (>= 16 each). ``fx = fy = 0.8 * width``,
            ``cx = (width - 1) / 2``, ``cy = (height - 1) / 2``.
        seed: selects the sensor-noise realisation (the scene and trajectories do not depend on it).
        depth_noise: Kinect-like depth noise ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` m plus holes
            (depth discontinuities, grazing angles, random blobs and dropouts). False = exact depth.
        rgb_noise: standard deviation of additive Gaussian colour noise (0 = none). Colours are
            always quantised to 8 bits (multiples of 1/255), like a real camera.
        camera_speed: time scale of the camera trajectory (0 = still camera).
        object_speed: time scale of the cube's motion (0 = the cube stays at its initial pose).
        cache_dir: directory for rendered frames (``~`` expanded), or None for no caching. Frames go
            to ``cache_dir/cube-<hash of render parameters>/frame_NNNNN.npz``.

    Ground truth for evaluation (all in the world/room frame, float64):
        :meth:`camera_pose`, :meth:`camera_pose_at`, :meth:`object_poses`, :attr:`object_names`,
        :meth:`dynamic_box`, :meth:`sdf`, :meth:`sample_surface`, :meth:`raycast`, :meth:`render`.
    """

    name = "cube"
    has_gt_poses = True
    has_masks = True
    object_names = ["cube"]
    room_min = ROOM_MIN
    room_max = ROOM_MAX

    def __init__(
        self,
        num_frames: int = 150,
        fps: float = 30.0,
        width: int = 640,
        height: int = 480,
        seed: int = 0,
        depth_noise: bool = True,
        camera_speed: float = 1.0,
        object_speed: float = 1.0,
        cache_dir: str | os.PathLike | None = None,
        rgb_noise: float = 0.01,
    ) -> None:
        def bad(param: str, problem: str) -> DatasetError:
            return DatasetError(f"dataset.{param}", problem)

        def is_int(x: object, lowest: int) -> bool:
            return isinstance(x, (int, float, np.integer)) and not isinstance(x, bool) and float(x).is_integer() and x >= lowest

        if not is_int(num_frames, 1):
            raise bad("num_frames", f"must be an integer >= 1, got {num_frames!r}")
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise bad("fps", f"must be a finite number > 0, got {fps!r}")
        for pname, val in (("width", width), ("height", height)):
            if not is_int(val, 16):
                raise bad(pname, f"must be an integer >= 16 pixels, got {val!r}")
        if not is_int(seed, 0):
            raise bad("seed", f"must be a non-negative integer, got {seed!r}")
        for pname, val in (("camera_speed", camera_speed), ("object_speed", object_speed)):
            if not (isinstance(val, (int, float)) and math.isfinite(val)):
                raise bad(pname, f"must be a finite number, got {val!r}")
        if not (isinstance(rgb_noise, (int, float)) and math.isfinite(rgb_noise) and 0 <= rgb_noise <= 0.5):
            raise bad("rgb_noise", f"must be within [0, 0.5], got {rgb_noise!r}")

        self.num_frames = int(num_frames)
        self.fps = float(fps)
        self.width, self.height = int(width), int(height)
        self.seed = int(seed)
        self.depth_noise = bool(depth_noise)
        self.rgb_noise = float(rgb_noise)
        self.camera_speed = float(camera_speed)
        self.object_speed = float(object_speed)
        f = 0.8 * self.width
        self.intrinsics = Intrinsics(f, f, (self.width - 1) / 2.0, (self.height - 1) / 2.0, self.width, self.height)
        self.timestamps = np.arange(self.num_frames, dtype=np.float64) / self.fps

        self.cache_path: Path | None = None
        if cache_dir is not None and str(cache_dir) != "":
            self.cache_path = Path(os.path.expanduser(str(cache_dir))) / f"cube-{self.render_key()}"
        self._cache_warned = False
        # Camera-frame unit-z ray directions of every pixel, (H*W, 3) float64.
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=torch.float64), torch.arange(self.width, dtype=torch.float64), indexing="ij"
        )
        K = self.intrinsics
        self._rays_cam = torch.stack(
            [(u - K.cx) / K.fx, (v - K.cy) / K.fy, torch.ones_like(u)], dim=-1
        ).reshape(-1, 3)

    # ------------------------------------------------------------------------------------------
    # Parameters / cache key
    # ------------------------------------------------------------------------------------------

    def render_params(self) -> dict[str, object]:
        """Everything that determines the pixels of frame ``i`` (``num_frames`` does not)."""
        return {
            "version": RENDER_VERSION,
            "fps": self.fps,
            "width": self.width,
            "height": self.height,
            "seed": self.seed,
            "depth_noise": self.depth_noise,
            "rgb_noise": self.rgb_noise,
            "camera_speed": self.camera_speed,
            "object_speed": self.object_speed,
        }

    def render_key(self) -> str:
        """Short hash of :meth:`render_params` (names the cache folder)."""
        text = json.dumps(self.render_params(), sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:12]

    # ------------------------------------------------------------------------------------------
    # Ground-truth motion
    # ------------------------------------------------------------------------------------------

    def camera_pose_at(self, t: float) -> torch.Tensor:
        """(4, 4) float64 camera-to-world pose at time ``t`` seconds.

        A slow arc/dolly in front of the scene looking at a slowly drifting target, plus small
        multi-frequency hand-held jitter (a few mm, a few tenths of a degree). Bounded for any ``t``.
        """
        s = self.camera_speed * float(t)
        pos = np.array(
            [
                0.70 * math.sin(0.45 * s - 1.0),
                -1.00 + 0.22 * math.sin(0.31 * s + 0.4),
                1.35 + 0.10 * math.sin(0.53 * s + 0.2),
            ]
        )
        target = np.array([0.12 * math.sin(0.21 * s + 0.5), 0.45, 0.85 + 0.05 * math.sin(0.37 * s)])
        # Hand-held jitter: incommensurate frequencies (Hz), amplitudes in metres / radians.
        jit = np.array(
            [
                0.0030 * math.sin(2 * math.pi * 0.83 * s + 0.3) + 0.0012 * math.sin(2 * math.pi * 2.71 * s + 1.1),
                0.0025 * math.sin(2 * math.pi * 0.61 * s + 2.0) + 0.0010 * math.sin(2 * math.pi * 3.13 * s + 0.5),
                0.0030 * math.sin(2 * math.pi * 0.97 * s + 0.9) + 0.0012 * math.sin(2 * math.pi * 2.39 * s + 2.6),
            ]
        )
        ang = np.radians(
            [
                0.30 * math.sin(2 * math.pi * 0.71 * s + 0.7) + 0.10 * math.sin(2 * math.pi * 1.93 * s + 1.9),
                0.30 * math.sin(2 * math.pi * 0.53 * s + 2.3) + 0.10 * math.sin(2 * math.pi * 2.17 * s + 0.2),
                0.25 * math.sin(2 * math.pi * 0.89 * s + 1.4) + 0.08 * math.sin(2 * math.pi * 1.61 * s + 2.8),
            ]
        )
        R = _look_at(pos, target) @ _rot_x(ang[0]) @ _rot_y(ang[1]) @ _rot_z(ang[2])
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = torch.from_numpy(R)
        T[:3, 3] = torch.from_numpy(pos + jit)
        return T

    def camera_pose(self, i: int) -> torch.Tensor:
        """(4, 4) float64 camera-to-world ground-truth pose of frame ``i``."""
        return self.camera_pose_at(float(self.timestamps[i]) if 0 <= i < len(self) else i / self.fps)

    def camera_poses(self) -> torch.Tensor:
        """(N, 4, 4) float64 ground-truth camera-to-world poses of all frames."""
        return torch.stack([self.camera_pose(i) for i in range(len(self))])

    def object_poses(self, t: float) -> dict[str, torch.Tensor]:
        """Object-to-world (4, 4) float64 pose of every moving object at time ``t`` seconds.

        The cube (0.36 m edges, object frame at its centre, axes along its edges) floats above the
        floor: about 0.7 m of smooth translation and ~70 degrees of rotation over the default 5 s.
        """
        s = self.object_speed * float(t)
        center = np.array(
            [
                0.45 * math.sin(0.35 * s - 0.9),
                0.25 + 0.10 * math.sin(0.50 * s),
                1.00 + 0.12 * math.sin(0.80 * s),
            ]
        )
        R = _rot_z(0.35 + 0.25 * s) @ _rot_x(0.25 * math.sin(0.40 * s) + 0.2) @ _rot_y(0.15 * math.sin(0.3 * s))
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = torch.from_numpy(R)
        T[:3, 3] = torch.from_numpy(center)
        return {"cube": T}

    def dynamic_box(self, t: float, name: str = "cube") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Oriented box of moving object ``name`` at time ``t``: center (3,), half_extents (3,), R (3, 3).

        A world point ``p`` is inside iff ``all(|R^T (p - center)| <= half_extents)``.
        """
        if name not in self.object_names:
            raise KeyError(f"unknown object {name!r}; objects: {self.object_names}")
        T = self.object_poses(t)[name]
        return T[:3, 3].clone(), torch.full((3,), CUBE_HALF, dtype=torch.float64), T[:3, :3].clone()

    # ------------------------------------------------------------------------------------------
    # Exact geometry
    # ------------------------------------------------------------------------------------------

    def _boxes(self, t: float) -> list[tuple[int, torch.Tensor, torch.Tensor, torch.Tensor]]:
        """(primitive id, center, half, R) of every box-shaped solid at time t (float64 tensors)."""
        c, h, R = self.dynamic_box(t)
        out = []
        for pid, (bc, bh, bR) in ((BOX_A, _BOX_A), (BOX_B, _BOX_B)):
            out.append((pid, torch.from_numpy(bc), torch.from_numpy(bh), torch.from_numpy(bR)))
        out.append((CUBE, c, h, R))
        return out

    def sdf(self, points: torch.Tensor, t: float, part: str = "all") -> torch.Tensor:
        """Exact signed distance (metres) of the scene at time ``t``.

        Args:
            points: (N, 3) world points.
            t: time in seconds.
            part: "all", "static" (room + static objects) or "dynamic" (moving objects only).
        Returns:
            (N,) float64: positive in free space (inside the room, outside all objects), negative
            inside solids (the objects, and anything beyond the room's walls).
        """
        p = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
        if part not in ("all", "static", "dynamic"):
            raise ValueError(f"part must be 'all', 'static' or 'dynamic', got {part!r}")
        d = torch.full((p.shape[0],), math.inf, dtype=torch.float64)
        if part in ("all", "static"):
            lo, hi = torch.tensor(ROOM_MIN, dtype=torch.float64), torch.tensor(ROOM_MAX, dtype=torch.float64)
            d = torch.minimum(d, -box_sdf(p - (lo + hi) / 2, (hi - lo) / 2))
            sc, sr = _SPHERE
            d = torch.minimum(d, (p - torch.from_numpy(sc)).norm(dim=-1) - sr)
        for pid, c, h, R in self._boxes(t):
            if (pid == CUBE) == (part == "static") and part != "all":
                continue
            d = torch.minimum(d, box_sdf((p - c) @ R, h))
        return d

    def _faces(self, t: float, part: str) -> list[tuple[int, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Planar rectangular faces: (primitive id, corner origin, edge u, edge v, outward-to-free-space normal)."""
        faces = []
        if part in ("all", "static"):
            lo, hi = np.array(ROOM_MIN), np.array(ROOM_MAX)
            for axis in range(3):
                a1, a2 = (axis + 1) % 3, (axis + 2) % 3
                for side, normal_sign in ((lo, 1.0), (hi, -1.0)):
                    o = lo.copy()
                    o[axis] = side[axis]
                    eu = np.zeros(3)
                    eu[a1] = hi[a1] - lo[a1]
                    ev = np.zeros(3)
                    ev[a2] = hi[a2] - lo[a2]
                    n = np.zeros(3)
                    n[axis] = normal_sign
                    faces.append((ROOM, *(torch.from_numpy(x) for x in (o, eu, ev, n))))
        for pid, c, h, R in self._boxes(t):
            if part == "static" and pid == CUBE or part == "dynamic" and pid != CUBE:
                continue
            for axis in range(3):
                a1, a2 = (axis + 1) % 3, (axis + 2) % 3
                for sign in (-1.0, 1.0):
                    n = R[:, axis] * sign
                    o = c + n * h[axis] - R[:, a1] * h[a1] - R[:, a2] * h[a2]
                    faces.append((pid, o, R[:, a1] * 2 * h[a1], R[:, a2] * 2 * h[a2], n))
        return faces

    def sample_surface(self, t: float, n: int, part: str = "all", seed: int = 0) -> torch.Tensor:
        """Points sampled uniformly by area on the scene's surfaces at time ``t``.

        Args:
            t: time in seconds (moving objects are placed at their pose at ``t``).
            n: number of points.
            part: "all", "static" (room walls/floor/ceiling + static objects) or "dynamic".
            seed: random seed.
        Returns:
            (n, 3) float64 world points. Surface that is not visible from free space (box bottoms on
            the floor, the floor under the boxes) is excluded by rejection.
        """
        if part not in ("all", "static", "dynamic"):
            raise ValueError(f"part must be 'all', 'static' or 'dynamic', got {part!r}")
        if n <= 0:
            return torch.zeros(0, 3, dtype=torch.float64)
        gen = torch.Generator().manual_seed(int(seed))
        faces = self._faces(t, part)
        areas = torch.stack([torch.linalg.cross(eu, ev).norm() for _, _, eu, ev, _ in faces])
        origins = torch.stack([f[1] for f in faces])
        eus = torch.stack([f[2] for f in faces])
        evs = torch.stack([f[3] for f in faces])
        normals = torch.stack([f[4] for f in faces])
        sphere_area = 0.0
        if part in ("all", "static"):
            sphere_area = 4 * math.pi * _SPHERE[1] ** 2
        weights = torch.cat([areas, torch.tensor([sphere_area], dtype=torch.float64)])
        chunks, have = [], 0
        for _ in range(50):
            if have >= n:
                break
            m = max(64, int(1.3 * (n - have)) + 16)
            k = torch.multinomial(weights, m, replacement=True, generator=gen)
            uv = torch.rand(m, 2, generator=gen, dtype=torch.float64)
            on_sphere = k == len(faces)
            kf = k.clamp_max(len(faces) - 1)
            pts = origins[kf] + uv[:, :1] * eus[kf] + uv[:, 1:] * evs[kf]
            nrm = normals[kf]
            if on_sphere.any():
                g = torch.randn(int(on_sphere.sum()), 3, generator=gen, dtype=torch.float64)
                g = g / g.norm(dim=-1, keepdim=True)
                pts[on_sphere] = torch.from_numpy(_SPHERE[0]) + _SPHERE[1] * g
                nrm[on_sphere] = g
            # Keep points whose free-space side is really free (1 mm off the surface along the normal).
            free = self.sdf(pts + 1e-3 * nrm, t) > 5e-4
            chunks.append(pts[free])
            have += int(free.sum())
        return torch.cat(chunks)[:n]

    def raycast(self, c2w: torch.Tensor, t: float, rays_cam: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Cast rays through the scene at time ``t``.

        Args:
            c2w: (4, 4) camera-to-world pose.
            t: time in seconds (places the moving objects).
            rays_cam: (N, 3) camera-frame directions with z = 1; default: every pixel, row-major.
        Returns:
            dict with ``depth`` (N,) float64 z-depth of the first hit (inf = no hit; never happens
            inside the room), ``prim`` (N,) int64 primitive id (0 room, 1 box_a, 2 box_b, 3 sphere,
            4 cube), ``local`` (N, 3) hit point in the primitive's local frame, ``normal`` (N, 3)
            unit normal in that local frame (towards the camera's side), ``cos`` (N,) |cosine| of the
            angle between the normalised ray and the normal.
        """
        c2w = torch.as_tensor(c2w, dtype=torch.float64)
        d_cam = self._rays_cam if rays_cam is None else torch.as_tensor(rays_cam, dtype=torch.float64).reshape(-1, 3)
        R_wc, o = c2w[:3, :3], c2w[:3, 3]
        d = d_cam @ R_wc.T  # world directions; ray parameter = z-depth
        N = d.shape[0]
        inf = torch.full((N,), math.inf, dtype=torch.float64)

        def safe(x: torch.Tensor) -> torch.Tensor:
            return torch.where(x.abs() < 1e-12, torch.full_like(x, 1e-12), x)

        # Room interior: the exit point of the room box.
        lo, hi = torch.tensor(ROOM_MIN, dtype=torch.float64), torch.tensor(ROOM_MAX, dtype=torch.float64)
        ds = safe(d)
        tf = torch.maximum((lo - o) / ds, (hi - o) / ds)
        best_t, axis = tf.min(dim=-1)
        best_prim = torch.zeros(N, dtype=torch.int64)
        local = o + best_t[:, None] * d
        normal = torch.zeros(N, 3, dtype=torch.float64)
        normal.scatter_(1, axis[:, None], -torch.sign(ds.gather(1, axis[:, None])))
        nworld = normal

        for pid, c, h, R in self._boxes(t):
            ol = (o - c) @ R
            dl = safe(d @ R)
            t1 = (-h - ol) / dl
            t2 = (h - ol) / dl
            tnear, ax = torch.minimum(t1, t2).max(dim=-1)
            tfar = torch.maximum(t1, t2).min(dim=-1).values
            hit = (tnear <= tfar) & (tnear > 1e-9) & (tnear < best_t)
            if not hit.any():
                continue
            best_t = torch.where(hit, tnear, best_t)
            best_prim = torch.where(hit, torch.full_like(best_prim, pid), best_prim)
            local = torch.where(hit[:, None], ol + tnear[:, None] * dl, local)
            nl = torch.zeros(N, 3, dtype=torch.float64)
            nl.scatter_(1, ax[:, None], -torch.sign(dl.gather(1, ax[:, None])))
            normal = torch.where(hit[:, None], nl, normal)
            nworld = torch.where(hit[:, None], nl @ R.T, nworld)

        sc, sr = torch.from_numpy(_SPHERE[0]), _SPHERE[1]
        oc = o - sc
        a = (d * d).sum(-1)
        b = d @ oc
        disc = b * b - a * (oc @ oc - sr * sr)
        ts = (-b - disc.clamp_min(0).sqrt()) / a
        hit = (disc >= 0) & (ts > 1e-9) & (ts < best_t)
        if hit.any():
            best_t = torch.where(hit, ts, best_t)
            best_prim = torch.where(hit, torch.full_like(best_prim, SPHERE), best_prim)
            pl = oc + ts[:, None] * d
            local = torch.where(hit[:, None], pl, local)
            normal = torch.where(hit[:, None], pl / sr, normal)
            nworld = torch.where(hit[:, None], pl / sr, nworld)

        cos = (nworld * d).sum(-1).abs() / d.norm(dim=-1)
        return {"depth": best_t, "prim": best_prim, "local": local, "normal": normal, "cos": cos}

    # ------------------------------------------------------------------------------------------
    # Rendering
    # ------------------------------------------------------------------------------------------

    @staticmethod
    def shade(prim: torch.Tensor, local: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        """Noise-free colour (N, 3) float32 in [0, 1] of surface points given in their primitive's frame."""
        N = prim.shape[0]
        rgb = torch.zeros(N, 3, dtype=torch.float32)
        light = torch.from_numpy(_LIGHT)
        axis = normal.abs().argmax(dim=-1)
        face = 2 * axis + (normal.gather(1, axis[:, None])[:, 0] > 0).long()
        sid = 8 * prim + torch.where(prim == ROOM, face, torch.zeros_like(face))
        for key, surf in _SURFACES.items():
            sel = sid == key
            if not sel.any():
                continue
            p = local[sel]
            n1 = fbm(p, surf.salt)
            n1 = ((n1 - 0.5) * 2.4 + 0.5).clamp(0, 1)
            a, b, c, dd = (torch.tensor(x, dtype=torch.float32) for x in (surf.a, surf.b, surf.c, surf.d))
            col = a + b * torch.cos(2 * math.pi * (c * n1[:, None] + dd))
            lam = (normal[sel] @ light).to(torch.float32)
            shade = 0.55 + 0.45 * (0.5 + 0.5 * lam)
            rgb[sel] = (col * shade[:, None]).clamp(0, 1)
        return rgb

    def _rng(self, i: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, int(i), RENDER_VERSION, 7919])

    def render(self, i: int, noise: bool = True) -> Frame:
        """Render frame ``i`` (no cache). ``noise=False`` gives exact depth and noise-free colour."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for {self.name} with {len(self)} frames")
        H, W = self.height, self.width
        t = float(self.timestamps[i])
        pose = self.camera_pose(i)
        hit = self.raycast(pose, t)
        rgb = self.shade(hit["prim"], hit["local"], hit["normal"]).reshape(H, W, 3)
        depth = hit["depth"].reshape(H, W)
        mask = (hit["prim"] == CUBE).reshape(H, W)
        rng = self._rng(i)
        if noise and self.rgb_noise > 0:
            rgb = rgb + torch.from_numpy(rng.standard_normal((H, W, 3), dtype=np.float32) * self.rgb_noise)
        # 8-bit camera: quantise (the cache stores exactly these uint8 values).
        rgb8 = (rgb.clamp(0, 1) * 255.0).round().to(torch.uint8)
        if noise and self.depth_noise:
            depth = self._noisy_depth(depth, hit["cos"].reshape(H, W), rng)
        return self._frame(i, rgb8, depth.to(torch.float32), mask)

    def _noisy_depth(self, depth: torch.Tensor, cos: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """Kinect-like depth: axial noise growing with z^2 plus holes."""
        H, W = depth.shape
        z = depth.numpy()
        sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
        noisy = z + sigma * rng.standard_normal((H, W))
        hole = np.zeros((H, W), dtype=bool)
        # Depth discontinuities (object silhouettes): dilated band, mostly dropped.
        jump = np.zeros((H, W), dtype=bool)
        dx = np.abs(np.diff(z, axis=1)) > 0.04 * z[:, 1:]
        dy = np.abs(np.diff(z, axis=0)) > 0.04 * z[1:, :]
        jump[:, 1:] |= dx
        jump[:, :-1] |= dx
        jump[1:, :] |= dy
        jump[:-1, :] |= dy
        r = max(1, round(W / 320))
        band = F.max_pool2d(torch.from_numpy(jump)[None, None].float(), 2 * r + 1, stride=1, padding=r)[0, 0].numpy() > 0
        hole |= band & (rng.random((H, W)) < 0.6)
        # Grazing angles.
        hole |= (cos.numpy() < 0.12) & (rng.random((H, W)) < 0.5)
        # Random elliptical blobs (specularities / absorbing patches).
        vv, uu = np.mgrid[0:H, 0:W]
        for _ in range(int(rng.poisson(4))):
            cu, cv = rng.uniform(0, W), rng.uniform(0, H)
            ru, rv = rng.uniform(0.006, 0.025, size=2) * W
            hole |= ((uu - cu) / ru) ** 2 + ((vv - cv) / rv) ** 2 <= 1.0
        # Sparse dropouts.
        hole |= rng.random((H, W)) < 0.005
        noisy = np.where(hole, 0.0, np.clip(noisy, 0.0, None))
        return torch.from_numpy(noisy)

    def _frame(self, i: int, rgb8: torch.Tensor, depth: torch.Tensor, mask: torch.Tensor) -> Frame:
        frame = Frame(
            index=int(i),
            timestamp=float(self.timestamps[i]),
            rgb=rgb8.to(torch.float32) / 255.0,
            depth=depth.contiguous(),
            mask=mask.contiguous(),
            gt_pose=self.camera_pose(i),
        )
        return frame.validate(f"{self.name} frame {i}", self.intrinsics)

    # ------------------------------------------------------------------------------------------
    # Dataset API + cache
    # ------------------------------------------------------------------------------------------

    def _cache_file(self, i: int) -> Path | None:
        return None if self.cache_path is None else self.cache_path / f"frame_{i:05d}.npz"

    def _read_cache(self, path: Path, i: int) -> Frame | None:
        try:
            with np.load(path, allow_pickle=False) as z:
                rgb8, depth, mask = z["rgb"], z["depth"], z["mask"]
            H, W = self.height, self.width
            if rgb8.shape != (H, W, 3) or rgb8.dtype != np.uint8 or depth.shape != (H, W) or depth.dtype != np.float32:
                return None
            if mask.shape != (H, W) or mask.dtype != np.bool_:
                return None
            return self._frame(i, torch.from_numpy(rgb8), torch.from_numpy(depth), torch.from_numpy(mask))
        except Exception:  # noqa: BLE001 -- any unreadable / truncated / foreign file is re-rendered
            return None

    def _write_cache(self, path: Path, frame: Frame) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            params = path.parent / "params.json"
            if not params.exists():
                self._atomic_write(params, json.dumps(self.render_params(), indent=1, sort_keys=True).encode())
            rgb8 = (frame.rgb * 255.0).round().to(torch.uint8).numpy()
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
            try:
                with os.fdopen(fd, "wb") as fh:
                    np.savez_compressed(fh, rgb=rgb8, depth=frame.depth.numpy(), mask=frame.mask.numpy())
                os.chmod(tmp, 0o644)  # mkstemp creates 0600
                os.replace(tmp, path)
            except BaseException:
                if os.path.exists(tmp):
                    os.unlink(tmp)
                raise
        except OSError as exc:
            if not self._cache_warned:
                warnings.warn(f"{path.parent}: cannot write the frame cache ({exc}); rendering without it")
                self._cache_warned = True

    @staticmethod
    def _atomic_write(path: Path, data: bytes) -> None:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)

    def load_frame(self, i: int) -> Frame:
        path = self._cache_file(i)
        if path is not None and path.is_file():
            frame = self._read_cache(path, i)
            if frame is not None:
                return frame
        frame = self.render(i, noise=True)
        if path is not None:
            self._write_cache(path, frame)
        return frame
