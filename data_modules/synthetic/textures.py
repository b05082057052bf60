"""Procedural, seeded surface textures: hashed value noise through a cosine palette.

A surface colour is a pure function of the point in its primitive's *local* frame, so a surface point
has the same noise-free colour in every frame, also on a moving object. The noise is multi-octave
hashed lattice value noise (:func:`fbm`); on a planar face the lattice coordinate across the face is a
constant, so :class:`PlaneNoise` pre-blends that axis once into a 2-D table per octave and a pixel
costs four table reads per octave instead of eight hashes (the same field up to float rounding).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["PlaneNoise", "Texture", "fbm", "pattern_value", "random_texture", "shade", "value_noise"]

_M32 = 0xFFFFFFFF
_PRIMES = (73856093, 19349663, 83492791)
OCTAVES = 5
BASE_FREQ = 2.3  # lattice cells per metre of the first octave
LACUNARITY = 2.31  # incommensurate, so octaves do not line up
GAIN = 0.62
# Light direction used for shading, expressed in each primitive's local frame (shading is baked into
# the surface: it does not change when the object moves).
LIGHT = tuple(float(x) for x in np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82]))


@dataclass(frozen=True)
class Texture:
    """Colour of a surface: ``palette(t) = a + b cos(2 pi (c t + d))`` of a noise value ``t``.

    Attributes:
        salt: selects an independent noise field.
        a, b, c, d: palette coefficients per channel (RGB).
        scale: noise frequency multiplier (2 = features half as large).
        contrast: stretch of the noise around 0.5 before the palette.
        pattern: "noise" (noise only), "checker" or "stripes" (a hard-edged pattern mixed in).
        pattern_size: period of the pattern, metres.
        pattern_mix: how strongly the pattern shifts the palette input.
    """

    salt: int
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    c: tuple[float, float, float]
    d: tuple[float, float, float]
    scale: float = 1.0
    contrast: float = 2.4
    pattern: str = "noise"
    pattern_size: float = 0.25
    pattern_mix: float = 0.0


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


def _octaves(scale: float) -> list[tuple[float, float, tuple[float, float, float]]]:
    """(frequency per metre, amplitude, lattice shift) of each octave."""
    out, freq, amp = [], BASE_FREQ * scale, 1.0
    for k in range(OCTAVES):
        out.append((freq, amp, (0.37 * k, 0.61 * k, 0.13 * k)))
        freq *= LACUNARITY
        amp *= GAIN
    return out


def fbm(p: torch.Tensor, salt: int = 0, scale: float = 1.0) -> torch.Tensor:
    """Multi-octave value noise, (N, 3) metres -> (N,) float32 roughly in [0, 1].

    Octave frequencies are incommensurate (about 2.3, 5.3, 12.2, 28, 64 per metre times ``scale``) and
    each octave is offset by an irrational shift, so the pattern does not repeat.
    """
    total = torch.zeros(p.shape[0], dtype=torch.float32, device=p.device)
    norm = 0.0
    for k, (freq, amp, shift) in enumerate(_octaves(scale)):
        total = total + amp * value_noise(p * freq + torch.tensor(shift, dtype=p.dtype, device=p.device), salt + 1013 * k)
        norm += amp
    return total / norm


class PlaneNoise:
    """:func:`fbm` restricted to an axis-aligned plane of a primitive's local frame, by table lookup.

    Args:
        axis: local axis normal to the plane (0, 1, 2).
        offset: the plane's coordinate along ``axis``.
        lo, hi: (3,) local bounds of the face (only the two in-plane axes are used).
        salt, scale: as in :func:`fbm`.
    """

    def __init__(self, axis: int, offset: float, lo: np.ndarray, hi: np.ndarray, salt: int, scale: float) -> None:
        self.axis = axis
        self.inplane = ((axis + 1) % 3, (axis + 2) % 3)
        self.tables: list[tuple[tuple[torch.Tensor, ...], tuple[float, float], int, float, float]] = []
        self.norm = 0.0
        for k, (freq, amp, shift) in enumerate(_octaves(scale)):
            cells, i0, j0, n2 = self._octave_table(offset, lo, hi, salt + 1013 * k, freq, shift)
            origin = (shift[self.inplane[0]] - i0, shift[self.inplane[1]] - j0)
            self.tables.append((cells, origin, n2, freq, amp))
            self.norm += amp

    def _octave_table(self, offset: float, lo: np.ndarray, hi: np.ndarray, salt: int, freq: float,
                      shift: tuple[float, float, float]) -> tuple[tuple[torch.Tensor, ...], int, int, int]:
        """Lattice values of one octave already interpolated across the plane, packed per cell.

        Returns four (n1 * n2,) tables, the corner values (00, 01, 10, 11) of every lattice cell, the
        lattice origin (i0, j0) and the row length n2.
        """
        a1, a2 = self.inplane
        q = torch.tensor(offset, dtype=torch.float64) * freq + shift[self.axis]
        qf = torch.floor(q)
        fz = (q - qf).to(torch.float32)
        wz = fz * fz * (3.0 - 2.0 * fz)
        # One spare cell on each side: hit points may sit a rounding error outside the face.
        i0 = math.floor(lo[a1] * freq + shift[a1]) - 1
        j0 = math.floor(lo[a2] * freq + shift[a2]) - 1
        n1 = math.floor(hi[a1] * freq + shift[a1]) + 3 - i0
        n2 = math.floor(hi[a2] * freq + shift[a2]) + 3 - j0
        ii, jj = torch.meshgrid(torch.arange(i0, i0 + n1 + 1), torch.arange(j0, j0 + n2 + 1), indexing="ij")
        idx = torch.zeros(ii.numel(), 3, dtype=torch.int64)
        idx[:, a1], idx[:, a2] = ii.reshape(-1), jj.reshape(-1)
        layers = []
        for dk in (0, 1):
            idx[:, self.axis] = int(qf) + dk
            h = idx[:, 0] * _PRIMES[0] ^ idx[:, 1] * _PRIMES[1] ^ idx[:, 2] * _PRIMES[2] ^ salt
            layers.append(_hash_to_unit(h))
        grid = (layers[0] + (layers[1] - layers[0]) * wz).reshape(n1 + 1, n2 + 1)
        cells = tuple(c.reshape(-1).contiguous() for c in (grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]))
        return cells, i0, j0, n2

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        """(3, N) coordinate-major local points on the plane -> (N,) float32, equal to ``fbm(p.T)`` up
        to float rounding."""
        u, v = p[self.inplane[0]], p[self.inplane[1]]
        total = torch.zeros(p.shape[1], dtype=torch.float32)
        for (c00, c01, c10, c11), (ou, ov), n2, freq, amp in self.tables:
            # Lattice coordinates relative to the table origin (>= 0, so truncation is the floor).
            qu, qv = u * freq + ou, v * freq + ov
            fu, fv = torch.frac(qu).to(torch.float32), torch.frac(qv).to(torch.float32)
            wu, wv = fu * fu * (3.0 - 2.0 * fu), fv * fv * (3.0 - 2.0 * fv)
            cell = (qu.to(torch.int64) * n2 + qv.to(torch.int64)).clamp_(0, c00.shape[0] - 1)
            # Interpolate along the first in-plane axis, then the second.
            r0 = torch.lerp(c00.index_select(0, cell), c10.index_select(0, cell), wu)
            r1 = torch.lerp(c01.index_select(0, cell), c11.index_select(0, cell), wu)
            total += amp * torch.lerp(r0, r1, wv)
        return total / self.norm


def pattern_value(p: torch.Tensor, texture: Texture) -> torch.Tensor:
    """(3, N) coordinate-major local points -> (N,) float32 in {0, 1}: the texture's hard-edged pattern."""
    if texture.pattern == "noise" or texture.pattern_mix == 0.0:
        return torch.zeros(p.shape[1], dtype=torch.float32)
    cells = torch.floor(p / texture.pattern_size).to(torch.int64)
    if texture.pattern == "checker":
        return ((cells[0] + cells[1] + cells[2]) % 2).to(torch.float32)
    if texture.pattern == "stripes":
        return (cells[2] % 2).to(torch.float32)  # horizontal bands in the local frame
    raise ValueError(f"unknown texture pattern {texture.pattern!r}")


def shade(texture: Texture, noise: torch.Tensor, p: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Noise-free colour of surface points.

    Args:
        texture: the surface's texture.
        noise: (N,) float32 :func:`fbm` value of each point.
        p: (3, N) coordinate-major local points (for the pattern).
        normal: (3, N) local unit normals, or (3, 1) for a planar face (for the baked half-Lambert
            shading with the fixed local :data:`LIGHT`).
    Returns:
        (N, 3) float32 RGB in [0, 1].
    """
    n1 = ((noise - 0.5) * texture.contrast + 0.5).clamp(0, 1)
    if texture.pattern_mix:
        n1 = n1 + texture.pattern_mix * pattern_value(p, texture)
    a, b, c, d = (torch.tensor(x, dtype=torch.float32) for x in (texture.a, texture.b, texture.c, texture.d))
    col = a + b * torch.cos(2 * math.pi * (c * n1[:, None] + d))
    lam = (torch.tensor(LIGHT, dtype=normal.dtype) @ normal).to(torch.float32)
    light = 0.55 + 0.45 * (0.5 + 0.5 * lam)
    return (col * light[:, None]).clamp(0, 1)


def random_texture(rng: np.random.Generator, kind: str = "wall") -> Texture:
    """A random texture: muted palettes for room surfaces ("wall"), saturated ones for "object"s."""
    salt = int(rng.integers(1, 2**20))
    if kind == "wall":
        a = tuple(float(x) for x in rng.uniform(0.45, 0.66, 3))
        b = tuple(float(x) for x in rng.uniform(0.15, 0.28, 3))
        pattern = str(rng.choice(["noise", "noise", "checker", "stripes"]))
        mix = 0.0 if pattern == "noise" else float(rng.uniform(0.15, 0.3))
        size = float(rng.uniform(0.3, 0.6))
    elif kind == "object":
        a = tuple(float(x) for x in rng.uniform(0.35, 0.7, 3))
        b = tuple(float(x) for x in rng.uniform(0.28, 0.38, 3))
        pattern = str(rng.choice(["noise", "checker", "stripes"]))
        mix = 0.0 if pattern == "noise" else float(rng.uniform(0.25, 0.45))
        size = float(rng.uniform(0.06, 0.15))
    else:
        raise ValueError(f"kind must be 'wall' or 'object', got {kind!r}")
    c = tuple(float(x) for x in rng.uniform(0.8, 1.6, 3))
    d = tuple(float(x) for x in rng.uniform(0.0, 1.0, 3))
    scale = float(rng.uniform(0.8, 1.4))
    return Texture(salt, a, b, c, d, scale=scale, pattern=pattern, pattern_size=size, pattern_mix=mix)
