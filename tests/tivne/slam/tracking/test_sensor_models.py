"""tivne.slam.tracking.sensor, the sensor models of the odometry: a rolling shutter's row times and motion."""

from __future__ import annotations

import torch

from tivne.geometry import se3_exp, transform_points
from tivne.slam.tracking.sensor import Shutter, frame_shutters

XI = torch.tensor([0.3, -0.1, 0.2, 0.5, 2.0, -0.4], dtype=torch.float64)  # (v m/s, ω rad/s)


def test_rows_are_seen_around_the_middle_row_over_the_readout():
    shutter = Shutter(0.03, XI)
    t = shutter.row_times(torch.tensor([0.0, 59.5, 119.0]), 120)
    assert torch.allclose(t, torch.tensor([-0.03 * 59.5 / 120, 0.0, 0.03 * 59.5 / 120]))
    # a coarser level's row covers two finer rows: it is seen at their mean time
    assert torch.allclose(shutter.row_times(torch.tensor([0.0, 29.5, 59.0]), 60), shutter.row_times(torch.tensor([0.5, 59.5, 118.5]), 120))


def test_motion_is_the_twist_to_first_order():
    p = torch.tensor([[0.2, -0.3, 1.5], [-0.5, 0.4, 2.5]], dtype=torch.float64).T
    for dt in (1e-3, 1e-2):
        exact = transform_points(se3_exp(dt * XI), p.T).T  # a point the camera dt later sees at p, in the camera before
        first = p + Shutter(0.03, XI).motion(p, torch.full((2,), dt, dtype=torch.float64))
        assert (exact - first).abs().max() < 2 * dt**2 * 5  # second order in dt


def test_the_velocity_of_an_estimate_comes_from_the_previous_pose():
    T = se3_exp(torch.tensor([0.1, 0.0, -0.05, 0.02, -0.1, 0.03], dtype=torch.float64))  # T_ref_cur
    dt = 1 / 30
    previous = T @ se3_exp(-dt * XI)  # the frame before, in the reference's frame
    moving = Shutter(0.03, torch.zeros(6, dtype=torch.float64), previous, dt).at(T)
    assert torch.allclose(moving.velocity, XI, atol=1e-9)
    assert Shutter(0.03, XI).at(T).velocity is XI  # no previous pose: the velocity it was given


def test_a_frames_shutters_are_global_without_its_velocity_and_none_where_a_references_is_unknown():
    v = torch.tensor([0.1, 0.0, 0.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    assert frame_shutters(0.03, None, v) == ()
    current, known, unknown = frame_shutters(0.03, v, 2 * v, None)
    assert current.readout_s == 0.03 and torch.equal(current.velocity, v) and torch.equal(known.velocity, 2 * v) and unknown is None
