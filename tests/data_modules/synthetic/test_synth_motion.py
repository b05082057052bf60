"""Trajectories: rigid poses, the promised kinematics of each motion, camera paths and shake."""

from __future__ import annotations

import math

import numpy as np
import pytest

from data_modules.synthetic.motion import (
    CircleCurve,
    Fixed,
    LookAtCamera,
    Orbit,
    Shake,
    SineCurve,
    Slide,
    StopGo,
    Wobble,
    YawTarget,
    look_at,
)


def _is_rigid(T: np.ndarray) -> bool:
    R = T[:3, :3]
    return T.shape == (4, 4) and np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)


def _speed(motion, s: float, h: float = 1e-4) -> float:
    return float(np.linalg.norm(motion.pose(s + h)[:3, 3] - motion.pose(s - h)[:3, 3]) / (2 * h))


MOTIONS = [
    Fixed((1.0, 2.0, 0.3), 0.4),
    Wobble((0.0, 0.25, 1.0), (0.45, 0.1, 0.12), (0.35, 0.5, 0.8), (-0.9, 0, 0), yaw_rate=0.25, pitch_amp=0.25, pitch_freq=0.4),
    Slide((-1.0, 0.0, 0.5), (1.0, 0.0, 0.5), period=4.0, yaw_rate=0.5),
    Orbit((0.0, 0.0, 0.2), 0.6, 1.2, bob=0.1, bob_freq=2.0),
    StopGo((-1.0, 0.3, 0.2), (1.0, 0.3, 0.2), stop=1.0, move=1.2, turn=1.0),
]


@pytest.mark.parametrize("motion", MOTIONS, ids=lambda m: type(m).__name__)
def test_poses_are_rigid_and_bounded(motion):
    for s in np.linspace(-3.0, 40.0, 97):
        T = motion.pose(float(s))
        assert _is_rigid(T) and np.abs(T[:3, 3]).max() < 3.0


def test_slide_profiles():
    cos = Slide((-1.0, 0.0, 0.5), (1.0, 0.0, 0.5), period=4.0)
    assert np.allclose(cos.pose(0.0)[:3, 3], [-1, 0, 0.5]) and np.allclose(cos.pose(2.0)[:3, 3], [1, 0, 0.5])
    assert np.allclose(cos.pose(1.3)[:3, 3], cos.pose(5.3)[:3, 3])  # periodic
    assert _speed(cos, 1.0) == pytest.approx(math.pi * 2.0 / 4.0, rel=1e-6)  # peak pi |b - a| / period
    lin = Slide((-1.0, 0.0, 0.5), (1.0, 0.0, 0.5), period=4.0, profile="linear")
    assert [_speed(lin, s) for s in (0.3, 1.1, 2.7)] == pytest.approx([1.0] * 3, rel=1e-6)


def test_stop_go_rests_exactly_then_moves():
    m = StopGo((-1.0, 0.3, 0.2), (1.0, 0.3, 0.2), stop=1.0, move=1.2, turn=1.0)
    rest = [m.pose(s) for s in np.linspace(0.0, 0.99, 12)]
    assert all(np.array_equal(rest[0], T) for T in rest)  # zero velocity, bit for bit
    assert not m.moving(0.5) and m.moving(1.6) and not m.moving(2.5)
    assert _speed(m, 1.6) > 1.0
    assert np.allclose(m.pose(2.5)[:3, 3], [1.0, 0.3, 0.2]) and np.array_equal(m.pose(2.3), m.pose(3.1))
    assert np.allclose(m.pose(4.4)[:3, 3], [-1.0, 0.3, 0.2])  # back at the start after a full cycle


def test_orbit_and_turning_in_place():
    m = Orbit((0.5, -0.2, 0.3), 0.6, 1.2, phase=0.3)
    for s in (0.0, 0.7, 3.3):
        assert np.linalg.norm(m.pose(s)[:2, 3] - [0.5, -0.2]) == pytest.approx(0.6)
    spin = Orbit((0.5, -0.2, 0.3), 0.0, 0.0, spin=2.0)
    assert np.allclose(spin.pose(1.0)[:3, 3], spin.pose(0.0)[:3, 3])
    R = spin.pose(0.5)[:3, :3] @ spin.pose(0.0)[:3, :3].T
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(1.0)


def test_look_at_points_the_optical_axis_at_the_target():
    pos, target = np.array([0.3, -1.5, 1.4]), np.array([0.0, 0.5, 0.7])
    R = look_at(pos, target)
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[:, 2], (target - pos) / np.linalg.norm(target - pos))
    assert abs(R[2, 0]) < 1e-12 and R[2, 1] < 0  # x horizontal, image down = world down


def test_camera_paths_and_shake():
    still = LookAtCamera(SineCurve((0.0, -1.0, 1.4)), SineCurve((0.0, 1.0, 0.8)))
    assert np.array_equal(still.pose(0.0), still.pose(3.0))
    shaky = LookAtCamera(SineCurve((0.0, -1.0, 1.4)), SineCurve((0.0, 1.0, 0.8)), Shake(1.0))
    jitter = [np.linalg.norm(shaky.pose(s)[:3, 3] - still.pose(s)[:3, 3]) for s in np.linspace(0, 5, 50)]
    assert 0.001 < max(jitter) < 0.01  # a few millimetres
    assert np.array_equal(LookAtCamera(SineCurve((0.0, -1.0, 1.4)), SineCurve((0.0, 1.0, 0.8)), Shake(0.0)).pose(1.0), still.pose(1.0))
    orbit = CircleCurve((0.0, 0.0, 1.4), 1.8, 0.3)
    assert np.linalg.norm(orbit(2.0)[:2]) == pytest.approx(1.8)


def test_yaw_target_fast_turns():
    tgt = YawTarget((0.0, -1.5, 1.5), math.pi / 2, turn=1.4, hold=1.0, turn_time=0.5)
    assert tgt.yaw(0.5) == pytest.approx(math.pi / 2) and tgt.yaw(1.6) == pytest.approx(math.pi / 2 + 1.4)
    peak = max(abs(tgt.yaw(s + 1e-4) - tgt.yaw(s - 1e-4)) / 2e-4 for s in np.linspace(1.0, 1.5, 51))
    assert peak == pytest.approx(math.pi / 2 * 1.4 / 0.5, rel=1e-3)  # cosine ease: pi/2 * angle / time
    assert tgt(0.0)[2] == pytest.approx(1.0)  # drop 0.5 m below the origin


def test_hinge_turns_about_its_line_and_breathe_scales_on_top_of_a_rigid_motion():
    import math as _math

    from data_modules.synthetic.motion import Breathe, Fixed, Hinge

    h = Hinge((0.5, 1.0, 0.4), arm=0.3, yaw0=0.0, amplitude=1.2, freq=2.0)
    for s in (0.0, 0.4, 1.0, 3.0):
        T = h.pose(s)
        assert np.allclose(T[:3, 3] - T[:3, 0] * 0.3, [0.5, 1.0, 0.4])  # the hinge line never moves
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
    assert h.angle(0.0) == 0.0 and abs(h.angle(_math.pi / 2.0) - 1.2) < 1e-12
    b = Breathe(Fixed((0.0, 0.0, 1.0)), depth=0.3, freq=1.0)
    assert np.allclose(b.pose(2.0), Fixed((0.0, 0.0, 1.0)).pose(2.0))
    assert b.scale(0.0) == 1.0 and abs(b.scale(_math.pi) - 0.7) < 1e-12
