"""ObjectTrack: SE(3) poses per τ, SLERP + lerp between observations, the box, state_dict; the motion math."""

from __future__ import annotations

import math

import pytest
import torch

from tivne.geometry import invert_pose, se3_exp
from tivne.slam.objects import ObjectTrack
from tivne.slam.objects.motion import camera_in_object, interpolate_se3, object_pose, odometry_init, within_motion_gate
from tivne.slam.objects.track import run_velocity


def _pose(*xi) -> torch.Tensor:
    return se3_exp(torch.tensor(xi, dtype=torch.float64))


def _rz(deg: float, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    T[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return T


def test_pose_at_interpolates_between_observations_and_continues_the_end_velocity_beyond():
    A, B = _rz(10, (0.0, 0.0, 1.0)), _rz(50, (1.0, 2.0, 1.0))
    track = ObjectTrack.from_poses(4, [0.5, 1.5], torch.stack([A, B]), name="box")
    assert track.observed_taus() == [0.5, 1.5] and len(track) == 2 and track.name == "box"
    mid = track.pose_at(1.0)
    torch.testing.assert_close(mid, _rz(30, (0.5, 1.0, 1.0)), atol=1e-12, rtol=0)  # angle and position halfway
    q = track.pose_at(0.75)
    torch.testing.assert_close(q, _rz(20, (0.25, 0.5, 1.0)), atol=1e-12, rtol=0)
    torch.testing.assert_close(track.pose_at(0.5), A)
    # beyond the ends: 40 deg and (1, 2, 0) m per τ unit go on (an object entering or leaving keeps moving)
    torch.testing.assert_close(track.pose_at(0.25), _rz(0, (-0.25, -0.5, 1.0)), atol=1e-9, rtol=0)
    torch.testing.assert_close(track.pose_at(2.0), _rz(70, (1.5, 3.0, 1.0)), atol=1e-9, rtol=0)
    single = ObjectTrack.from_poses(5, [0.5], A[None])
    torch.testing.assert_close(single.pose_at(3.0), A)  # one observation: no velocity, held
    assert track.pose_at(1.0).dtype == torch.float64 and track.pose_at(1.0).shape == (4, 4)


def test_add_keeps_order_and_replaces_the_same_tau():
    track = ObjectTrack(1)
    with pytest.raises(ValueError, match="no observed pose"):
        track.pose_at(0.0)
    track.add(2.0, _rz(20))
    track.add(1.0, _rz(10))
    track.add(2.0, _rz(40))
    assert track.observed_taus() == [1.0, 2.0]
    torch.testing.assert_close(track.pose_at(2.0), _rz(40))
    assert track.observed_near(1.9, 0.15) and not track.observed_near(1.5, 0.1)
    with pytest.raises(ValueError, match="finite"):
        track.add(3.0, torch.full((4, 4), float("nan")))


def test_a_pose_asked_for_before_a_new_observation_is_not_served_stale_after_it():
    track = ObjectTrack.from_poses(1, [0.0, 1.0], torch.stack([_rz(0), _rz(0, (1.0, 0.0, 0.0))]))
    assert torch.allclose(track.pose_at(1.0)[:3, 3], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    track.pose_at(1.0)[0, 3] = 99.0  # a caller's change never reaches the track
    track.add(1.0, _rz(0, (2.0, 0.0, 0.0)))  # replaced
    track.add(2.0, _rz(0, (3.0, 0.0, 0.0)))  # extended
    assert torch.allclose(track.pose_at(1.0)[:3, 3], torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64))
    assert torch.allclose(track.pose_at(1.5)[:3, 3], torch.tensor([2.5, 0.0, 0.0], dtype=torch.float64))
    restored = ObjectTrack.from_state_dict(ObjectTrack.from_poses(1, [1.0], _rz(0, (5.0, 0.0, 0.0))[None]).state_dict())
    track.load_state_dict(restored.state_dict())
    assert torch.allclose(track.pose_at(1.0)[:3, 3], torch.tensor([5.0, 0.0, 0.0], dtype=torch.float64))
    assert track.observed_near(1.2, 0.25) and not track.observed_near(1.3, 0.25) and not track.observed_near(0.7, 0.25)


def test_pose_at_turns_the_object_about_its_box_middle():
    # Observed turning 90 deg about z through (1, 0, 0) in object coordinates, the box around that point:
    # halfway the middle stays where it was and the object has turned 45 deg about it.
    A = _rz(0)
    B = _rz(90, (1.0, -1.0, 0.0))  # B maps (1, 0, 0) to (1, 0, 0)
    track = ObjectTrack.from_poses(1, [0.0, 1.0], torch.stack([A, B]))
    about_origin = track.pose_at(0.5)
    track.grow_box(torch.tensor([[0.8, -0.2, -0.2], [1.2, 0.2, 0.2]], dtype=torch.float64))
    mid = track.pose_at(0.5)  # not the pose cached before the box
    middle = torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(mid @ middle, middle, atol=1e-12, rtol=0)
    torch.testing.assert_close(mid[:3, :3], _rz(45)[:3, :3], atol=1e-12, rtol=0)
    assert float((about_origin @ middle - middle).norm()) > 0.2  # the chord of the middle's arc, about the origin


def test_box_and_state_dict_round_trip():
    track = ObjectTrack.from_poses(7, [0.0, 1.0], torch.stack([_rz(0), _rz(90, (1, 0, 0))]), name=None)
    assert track.box is None
    track.grow_box(torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 2.0]]))
    track.grow_box(torch.tensor([[-1.0, 0.5, 0.0], [float("nan"), 9.0, 9.0]]))  # non-finite rows ignored
    torch.testing.assert_close(track.box, torch.tensor([[-1.0, -1.0, 0.0], [1.0, 0.5, 2.0]], dtype=torch.float64))
    copy = ObjectTrack.from_state_dict(track.state_dict())
    assert (copy.object_id, copy.name, copy.observed_taus()) == (7, None, [0.0, 1.0])
    torch.testing.assert_close(copy.poses(), track.poses())
    torch.testing.assert_close(copy.box, track.box)
    torch.testing.assert_close(copy.pose_at(0.5), track.pose_at(0.5))


def test_geodesic_interpolation():
    A, xi = _pose(0.1, -0.2, 0.3, 0.2, 0.1, -0.3), torch.tensor([0.3, 0.1, -0.2, 0.0, 0.4, 0.2], dtype=torch.float64)
    B = A @ se3_exp(xi)
    torch.testing.assert_close(interpolate_se3(A, B, 0.0), A)
    torch.testing.assert_close(interpolate_se3(A, B, 1.0), B)
    torch.testing.assert_close(interpolate_se3(A, B, 0.25), A @ se3_exp(0.25 * xi))


def test_object_pose_inverts_the_object_frame_odometry():
    """T_wo_k = T_wc_k · T_ref_cur⁻¹ · C_r⁻¹ for the T_ref_cur = C_r⁻¹ C_k the object-pixel odometry sees."""
    T_wc_r, T_wc_k = _pose(0.1, 0.2, 0.0, 0.05, -0.1, 0.2), _pose(0.3, 0.1, -0.1, 0.0, 0.2, 0.1)
    T_wo_r, T_wo_k = _pose(1.0, 0.5, 2.0, 0.3, 0.0, 0.1), _pose(1.2, 0.4, 2.1, 0.1, 0.5, -0.2)
    C_r, C_k = camera_in_object(T_wo_r, T_wc_r), camera_in_object(T_wo_k, T_wc_k)
    T_ref_cur = invert_pose(C_r) @ C_k
    torch.testing.assert_close(object_pose(T_wc_k, T_ref_cur, C_r), T_wo_k)
    torch.testing.assert_close(odometry_init(T_wo_k, T_wc_k, C_r), T_ref_cur)
    # A static object: the odometry sees the camera's own motion.
    torch.testing.assert_close(odometry_init(T_wo_r, T_wc_k, C_r), invert_pose(T_wc_r) @ T_wc_k)


def test_the_motion_gate_scales_with_the_priors_sigma_over_the_time_step():
    pred = torch.eye(4, dtype=torch.float64)
    moved = pred.clone()
    moved[0, 3] = 0.02  # 2 cm; σ_t = ½ · 4 m/s² · (1/30 s)² = 2.2 mm
    assert within_motion_gate(moved, pred, 1 / 30, 4.0, 30.0, 10.0)
    assert not within_motion_gate(moved, pred, 1 / 30, 4.0, 30.0, 5.0)
    assert within_motion_gate(moved, pred, 0.1, 4.0, 30.0, 5.0)  # a longer step: σ_t 2 cm
    turned = pred.clone()
    a = math.radians(12.0)  # σ_r = ½ · 30 rad/s² · (1/30 s)² = 0.95°
    turned[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    assert not within_motion_gate(turned, pred, 1 / 30, 4.0, 30.0, 10.0)
    assert within_motion_gate(turned, pred, 1 / 30, 0.0, 30.0, 10.0)  # no prior, no gate


def test_a_velocity_is_read_within_the_last_run_of_views_or_across_a_gap():
    frame = 1 / 30
    run = [i * frame for i in range(5)]
    gap = run + [2.0 + i * frame for i in range(5)]  # a 1.87 s gap, then views again
    seconds = {t: t for t in gap}
    assert run_velocity(run[:1], seconds, 0.2) == (False, False)  # one view: no velocity
    assert run_velocity(run[:2], seconds, 0.2) == (True, True)  # a new track's views, no gap: read between them
    assert run_velocity(gap[:6], seconds, 0.2) == (False, False)  # one view after it: none
    assert run_velocity(gap[:8], seconds, 0.2) == (True, False)  # two frames after it: read across the gap
    assert run_velocity(gap[:9], seconds, 0.2) == (True, False)  # 0.1 s after it: pose_at's partner may still lie before it
    assert run_velocity(gap, seconds, 0.2) == (True, True)  # 0.133 s: read within the run
    assert run_velocity(gap[:7], seconds, 2.0) == (True, True)  # a gap under max_gap is no gap
    # the run's span is read in field time, as pose_at reads it
    assert run_velocity([2 * t for t in gap[:8]], {2 * t: t for t in gap}, 0.2) == (True, True)
    assert run_velocity([t / 2 for t in gap[:8]], {t / 2: t for t in gap}, 0.2) == (True, False)
