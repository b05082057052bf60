"""Rigid trajectories: object motions and camera paths, pure functions of (scaled) time.

Every trajectory maps a time ``s`` in seconds (the sequence time times a speed factor) to a (4, 4)
float64 numpy pose (object-to-world, or camera-to-world with OpenCV camera axes: x right, y down,
z forward), is defined and bounded for every ``s`` and is smooth unless its description says
otherwise. World frame: metres, z up, floor at z = 0.

Object motions: :class:`Fixed`, :class:`Wobble` (multi-sine drift and tumble), :class:`Slide`
(back and forth along a segment), :class:`Orbit` (circling; radius 0 = turning in place) and
:class:`StopGo` (moves, stops, moves back), :class:`Hinge` (a door swinging on a vertical hinge line) and
:class:`Breathe` (a rigid motion plus a uniform breathing scale of the shape: non-rigid). Camera paths: :class:`LookAtCamera` built from a
position and a target curve (:class:`SineCurve`, :class:`CircleCurve`, :class:`YawTarget`) plus
optional hand-held :class:`Shake`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Breathe",
    "CircleCurve",
    "Fixed",
    "Hinge",
    "LookAtCamera",
    "Motion",
    "Orbit",
    "Shake",
    "SineCurve",
    "Slide",
    "StopGo",
    "Wobble",
    "YawTarget",
    "ease",
    "look_at",
    "pose_matrix",
    "rot_x",
    "rot_y",
    "rot_z",
]

Vec3 = tuple[float, float, float]


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at(position: np.ndarray, target: np.ndarray, up: Vec3 = (0.0, 0.0, 1.0)) -> np.ndarray:
    """(3, 3) camera-to-world rotation (OpenCV axes) of a camera at ``position`` looking at ``target``."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = _cross(z, np.asarray(up, dtype=np.float64))
    x = x / np.linalg.norm(x)
    y = _cross(z, x)
    return np.stack([x, y, z], axis=1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two (3,) vectors (np.cross's arithmetic, without its per-call overhead)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def ease(u: float) -> float:
    """Cosine ease 0 -> 1 on u in [0, 1] with zero slope at both ends (clamped outside)."""
    u = min(max(u, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * u)


def _sines(base: Vec3, amp: Vec3, freq: Vec3, phase: Vec3, s: float) -> np.ndarray:
    """(3,) per-axis ``base + amp sin(freq s + phase)``."""
    return np.array([b + a * math.sin(f * s + p) for b, a, f, p in zip(base, amp, freq, phase)])


# --------------------------------------------------------------------------------- object motions


@dataclass(frozen=True)
class Fixed:
    """A static pose (object-to-world)."""

    center: Vec3
    yaw: float = 0.0

    def pose(self, s: float) -> np.ndarray:
        return pose_matrix(rot_z(self.yaw), np.asarray(self.center, dtype=np.float64))


@dataclass(frozen=True)
class Wobble:
    """Multi-sine drift of the centre and a tumble ``Rz(yaw0 + yaw_rate s) Rx(pitch0 + pitch_amp sin(pitch_freq s))
    Ry(roll_amp sin(roll_freq s))`` (angles in radians, frequencies in rad/s)."""

    base: Vec3
    amp: Vec3
    freq: Vec3
    phase: Vec3
    yaw0: float = 0.0
    yaw_rate: float = 0.0
    pitch0: float = 0.0
    pitch_amp: float = 0.0
    pitch_freq: float = 0.0
    roll_amp: float = 0.0
    roll_freq: float = 0.0

    def pose(self, s: float) -> np.ndarray:
        center = _sines(self.base, self.amp, self.freq, self.phase, s)
        R = (rot_z(self.yaw0 + self.yaw_rate * s) @ rot_x(self.pitch_amp * math.sin(self.pitch_freq * s) + self.pitch0)
             @ rot_y(self.roll_amp * math.sin(self.roll_freq * s)))
        return pose_matrix(R, center)


@dataclass(frozen=True)
class Slide:
    """Back and forth between ``start`` and ``end`` with period ``period`` seconds, turning about z.

    ``profile``: "cosine" (smooth, peak speed pi |end - start| / period) or "linear" (constant speed
    2 |end - start| / period, instant turn-around: put the ends outside the view for objects that
    enter and leave it). ``phase`` in seconds.
    """

    start: Vec3
    end: Vec3
    period: float
    phase: float = 0.0
    yaw0: float = 0.0
    yaw_rate: float = 0.0
    profile: str = "cosine"

    def fraction(self, s: float) -> float:
        """Position along the segment in [0, 1] at time ``s``."""
        u = ((s + self.phase) / self.period) % 1.0
        if self.profile == "linear":
            return 1.0 - abs(2.0 * u - 1.0)
        return 0.5 - 0.5 * math.cos(2.0 * math.pi * u)

    def pose(self, s: float) -> np.ndarray:
        a, b = np.asarray(self.start, dtype=np.float64), np.asarray(self.end, dtype=np.float64)
        return pose_matrix(rot_z(self.yaw0 + self.yaw_rate * s), a + (b - a) * self.fraction(s))


@dataclass(frozen=True)
class Orbit:
    """Circling ``center`` at ``radius`` (angle ``phase + rate s``, counter-clockwise seen from above),
    bobbing ``bob`` metres at ``bob_freq`` rad/s, turning about z at ``spin`` rad/s plus the orbit
    angle when ``face_motion``. ``radius = 0`` turns in place."""

    center: Vec3
    radius: float
    rate: float
    phase: float = 0.0
    spin: float = 0.0
    bob: float = 0.0
    bob_freq: float = 0.0
    face_motion: bool = True

    def pose(self, s: float) -> np.ndarray:
        ang = self.phase + self.rate * s
        c = np.asarray(self.center, dtype=np.float64)
        p = c + np.array([self.radius * math.cos(ang), self.radius * math.sin(ang), self.bob * math.sin(self.bob_freq * s)])
        yaw = self.spin * s + (ang if self.face_motion else 0.0)
        return pose_matrix(rot_z(yaw), p)


@dataclass(frozen=True)
class StopGo:
    """Rest at ``start`` for ``stop`` s, move to ``end`` in ``move`` s (cosine ease), rest, move back.

    During the rests the pose is exactly constant (zero velocity); the cycle repeats every
    ``2 (stop + move)`` seconds, shifted by ``phase`` seconds.
    """

    start: Vec3
    end: Vec3
    stop: float
    move: float
    phase: float = 0.0
    yaw0: float = 0.0
    turn: float = 0.0  # yaw change (rad) while moving start -> end

    def fraction(self, s: float) -> float:
        """Position along the segment in [0, 1] at time ``s``."""
        u = (s + self.phase) % (2.0 * (self.stop + self.move))
        leg = self.stop + self.move
        if u < leg:
            return ease((u - self.stop) / self.move)
        return 1.0 - ease((u - leg - self.stop) / self.move)

    def moving(self, s: float) -> bool:
        """True while the object moves at time ``s``."""
        u = (s + self.phase) % (self.stop + self.move)
        return u > self.stop

    def pose(self, s: float) -> np.ndarray:
        f = self.fraction(s)
        a, b = np.asarray(self.start, dtype=np.float64), np.asarray(self.end, dtype=np.float64)
        return pose_matrix(rot_z(self.yaw0 + self.turn * f), a + (b - a) * f)


@dataclass(frozen=True)
class Hinge:
    """A door turning about the vertical line through ``hinge`` (x, y; its z is the door's centre
    height). The door's local x axis points from the hinge line to its free edge, its centre
    ``arm`` metres from the line; the angle is ``yaw0 + amplitude (1 - cos(freq s)) / 2``: it
    swings from ``yaw0`` to ``yaw0 + amplitude`` and back, slowing at both ends."""

    hinge: Vec3
    arm: float
    yaw0: float
    amplitude: float
    freq: float

    def angle(self, s: float) -> float:
        return self.yaw0 + self.amplitude * (1.0 - math.cos(self.freq * s)) / 2.0

    def pose(self, s: float) -> np.ndarray:
        R = rot_z(self.angle(s))
        return pose_matrix(R, np.asarray(self.hinge, dtype=np.float64) + R[:, 0] * self.arm)


@dataclass(frozen=True)
class Breathe:
    """``base``'s rigid motion plus a uniform scale of the shape about its centre,
    ``1 - depth (1 - cos(freq s)) / 2``: 1 (the shape as given, its largest) down to ``1 - depth``
    and back. Not rigid: a deformation with an exact SDF (the scaled primitive's)."""

    base: Fixed | Wobble | Slide | Orbit | StopGo | Hinge
    depth: float
    freq: float

    def pose(self, s: float) -> np.ndarray:
        return self.base.pose(s)

    def scale(self, s: float) -> float:
        return 1.0 - self.depth * (1.0 - math.cos(self.freq * s)) / 2.0


Motion = Fixed | Wobble | Slide | Orbit | StopGo | Hinge | Breathe


# ----------------------------------------------------------------------------------- camera paths


@dataclass(frozen=True)
class SineCurve:
    """(3,) point ``base + amp sin(freq s + phase)`` per axis (rad/s)."""

    base: Vec3
    amp: Vec3 = (0.0, 0.0, 0.0)
    freq: Vec3 = (0.0, 0.0, 0.0)
    phase: Vec3 = (0.0, 0.0, 0.0)

    def __call__(self, s: float) -> np.ndarray:
        return _sines(self.base, self.amp, self.freq, self.phase, s)


@dataclass(frozen=True)
class CircleCurve:
    """Horizontal circle around ``center`` (angle ``phase + rate s``), height bobbing ``bob`` m."""

    center: Vec3
    radius: float
    rate: float
    phase: float = 0.0
    bob: float = 0.0
    bob_freq: float = 0.0

    def __call__(self, s: float) -> np.ndarray:
        ang = self.phase + self.rate * s
        return np.asarray(self.center, dtype=np.float64) + np.array(
            [self.radius * math.cos(ang), self.radius * math.sin(ang), self.bob * math.sin(self.bob_freq * s)]
        )


@dataclass(frozen=True)
class YawTarget:
    """A target ``distance`` m from ``origin`` in the horizontal direction ``yaw(s)`` (radians,
    0 = +x, counter-clockwise), ``drop`` m below the origin's height.

    ``yaw(s) = yaw0 + sweep sin(sweep_freq s)`` (a pan) plus ``turn`` rad turns: hold ``hold`` s, turn
    by ``turn`` in ``turn_time`` s (cosine ease), hold, turn back (fast turns).
    """

    origin: Vec3
    yaw0: float
    distance: float = 2.0
    drop: float = 0.5
    sweep: float = 0.0
    sweep_freq: float = 0.0
    turn: float = 0.0
    hold: float = 1.0
    turn_time: float = 0.5

    def yaw(self, s: float) -> float:
        y = self.yaw0 + self.sweep * math.sin(self.sweep_freq * s)
        if self.turn:
            y += self.turn * StopGo((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), self.hold, self.turn_time).fraction(s)
        return y

    def __call__(self, s: float) -> np.ndarray:
        a = self.yaw(s)
        o = np.asarray(self.origin, dtype=np.float64)
        return o + np.array([self.distance * math.cos(a), self.distance * math.sin(a), -self.drop])


# Hand-held jitter: (amplitude, frequency Hz, phase) pairs per axis; metres for the translation,
# degrees for the rotation about camera x, y, z.
_SHAKE_T = (((0.0030, 0.83, 0.3), (0.0012, 2.71, 1.1)), ((0.0025, 0.61, 2.0), (0.0010, 3.13, 0.5)),
            ((0.0030, 0.97, 0.9), (0.0012, 2.39, 2.6)))
_SHAKE_R = (((0.30, 0.71, 0.7), (0.10, 1.93, 1.9)), ((0.30, 0.53, 2.3), (0.10, 2.17, 0.2)),
            ((0.25, 0.89, 1.4), (0.08, 1.61, 2.8)))


@dataclass(frozen=True)
class Shake:
    """Multi-frequency hand-held jitter: ``scale`` 1 = a few mm and a few tenths of a degree."""

    scale: float = 1.0

    @staticmethod
    def _sum(terms, s: float) -> float:
        return sum(a * math.sin(2 * math.pi * f * s + p) for a, f, p in terms)

    def offset(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(3,) translation (m) and (3, 3) rotation (applied in the camera frame) at time ``s``."""
        jit = np.array([self.scale * self._sum(axis, s) for axis in _SHAKE_T])
        ang = np.radians([self._sum(axis, s) for axis in _SHAKE_R]) * self.scale
        return jit, rot_x(ang[0]) @ rot_y(ang[1]) @ rot_z(ang[2])


@dataclass(frozen=True)
class LookAtCamera:
    """Camera at ``position(s)`` looking at ``target(s)`` (z up), plus optional hand-held shake."""

    position: SineCurve | CircleCurve
    target: SineCurve | CircleCurve | YawTarget
    shake: Shake | None = field(default=None)

    def pose(self, s: float) -> np.ndarray:
        pos = self.position(s)
        R = look_at(pos, self.target(s))
        if self.shake is None or self.shake.scale == 0.0:
            return pose_matrix(R, pos)
        jit, R_shake = self.shake.offset(s)
        return pose_matrix(R @ R_shake, pos + jit)
