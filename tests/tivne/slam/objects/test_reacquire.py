"""Re-acquisition hypotheses and their choice (tivne.slam.objects.reacquire) and the centred prior."""

from __future__ import annotations

import math

import torch

from data_modules.poses import rotation_vector
from tivne.geometry import se3_exp
from tivne.slam.objects.motion import centred_information
from tivne.slam.objects.reacquire import Hypothesis, best_alignment, reacquired, rotation_hypotheses, spin_axis
from tivne.slam.tracking.odometry import OdometryResult


def result(overlap: float, inlier_ratio: float, rms_photometric: float, num_valid: int = 500) -> OdometryResult:
    eye = torch.eye(4, dtype=torch.float64)
    return OdometryResult(T_ref_cur=eye, converged=True, num_valid=num_valid, overlap=overlap, inlier_ratio=inlier_ratio,
                          rms_photometric=rms_photometric, rms_geometric=0.01, iterations=(3,), min_eigenvalue=1.0, condition=1.0,
                          pose_std=0.0, ok=True, information=torch.eye(6, dtype=torch.float64))


def test_hypotheses_turn_about_the_object_origin_in_even_steps():
    T = se3_exp(torch.tensor([0.3, -0.2, 1.0, 0.1, 0.2, -0.3], dtype=torch.float64))
    axes = torch.eye(3, dtype=torch.float64)
    hyps = rotation_hypotheses(T, axes, 90.0)
    assert len(hyps) == 1 + 3 * 3 and torch.equal(hyps[0], T)
    for k, H in enumerate(hyps[1:]):
        assert torch.allclose(H[:3, 3], T[:3, 3])  # the origin stays
        turn = rotation_vector(H[:3, :3] @ T[:3, :3].T)
        assert math.isclose(math.degrees(float(turn.norm())), (90.0, 180.0, 90.0)[k % 3], abs_tol=1e-6)
        assert torch.allclose(turn.abs() / turn.norm(), axes[k // 3], atol=1e-6)


def test_best_alignment_prefers_texture_among_equally_supported_poses():
    geometric_twin = Hypothesis(torch.eye(4, dtype=torch.float64), result(0.95, 1.0, 0.20))  # a box turned by 180°
    right = Hypothesis(2 * torch.eye(4, dtype=torch.float64), result(0.9, 0.98, 0.03))
    poor = Hypothesis(3 * torch.eye(4, dtype=torch.float64), result(0.3, 0.5, 0.01))  # lowest RMS on few pixels
    assert best_alignment([geometric_twin, right, poor]) is right
    assert best_alignment([Hypothesis(torch.eye(4)), Hypothesis(torch.eye(4), result(0.9, 1.0, 0.1, num_valid=0))]) is None
    no_colour = [Hypothesis(torch.eye(4), result(0.5, 1.0, math.nan)), right := Hypothesis(torch.eye(4), result(0.9, 1.0, math.nan))]
    assert best_alignment(no_colour) is right


def test_the_prediction_is_kept_unless_another_hypothesis_is_clearly_better():
    """A ball turned onto a side no stored view saw: every turn fits its geometry alike and none its
    texture better than the prediction does, so the prediction stays; a turn that explains the
    texture clearly better (or the pixels at all) replaces it."""
    prediction = Hypothesis(torch.eye(4, dtype=torch.float64), result(0.9, 1.0, 0.15))
    turned = Hypothesis(2 * torch.eye(4, dtype=torch.float64), result(0.92, 1.0, 0.14))
    assert best_alignment([turned, prediction], preferred=prediction) is prediction
    assert best_alignment([turned, prediction]) is turned  # without a preference: the lowest RMS
    textured = Hypothesis(3 * torch.eye(4, dtype=torch.float64), result(0.9, 1.0, 0.03))
    assert best_alignment([turned, textured, prediction], preferred=prediction) is textured
    unaligned = Hypothesis(torch.eye(4, dtype=torch.float64), result(0.9, 0.0, math.nan, num_valid=0))
    assert best_alignment([turned, unaligned], preferred=unaligned) is turned
    half = Hypothesis(torch.eye(4, dtype=torch.float64), result(0.4, 1.0, 0.13))  # explains less than 80 % as many pixels
    assert best_alignment([turned, half], preferred=half) is turned


def test_the_pose_that_fits_the_texture_wins_over_a_better_supported_turn():
    """Crossing's near box back after a gap (measured): the right pose sees less of its stored view
    (overlap 0.41) than a 90° turn sees of another (0.80), but only it fits the texture as the
    object's recent alignments did."""
    right = Hypothesis(torch.eye(4, dtype=torch.float64), result(0.41, 0.97, 0.022))
    turned = Hypothesis(2 * torch.eye(4, dtype=torch.float64), result(0.80, 0.86, 0.162))
    turned_too = Hypothesis(3 * torch.eye(4, dtype=torch.float64), result(0.87, 0.81, 0.166))
    prediction = Hypothesis(4 * torch.eye(4, dtype=torch.float64), result(0.41, 0.47, 0.134))
    refined = [right, turned, turned_too, prediction]
    assert reacquired(refined, prediction, typical_rms=0.0169) is right
    # nothing fits the texture that well: no turn is taken, the prediction stays
    assert reacquired(refined, prediction, typical_rms=0.005) is prediction
    # without a typical RMS (no recent alignment) the support and the texture decide as before
    assert reacquired(refined, prediction, typical_rms=math.nan) is turned


def test_centred_prior_penalises_a_spin_about_the_centre_as_a_rotation_only():
    centre = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    lam = centred_information(0.01, 0.1, centre)
    w = torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64)
    spin = torch.cat([-torch.linalg.cross(w, centre), w])  # the left twist turning about the centre: v = −w × c
    assert math.isclose(float(spin @ lam @ spin), float(w @ w) / 0.1**2, rel_tol=1e-9)
    slide = torch.tensor([0.02, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert math.isclose(float(slide @ lam @ slide), 0.02**2 / 0.01**2, rel_tol=1e-9)


def test_spin_axis_of_a_turning_track_and_none_for_a_sliding_one():
    taus = [0.1 * k for k in range(6)]
    axis = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    spinning = torch.stack([se3_exp(torch.cat([torch.tensor([0.05 * t, 0.0, 0.0], dtype=torch.float64), axis * t])) for t in taus])
    assert torch.allclose(spin_axis(taus, spinning, 0.3, 5.0), axis, atol=1e-9)
    sliding = torch.stack([se3_exp(torch.tensor([0.1 * t, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)) for t in taus])
    assert spin_axis(taus, sliding, 0.3, 5.0) is None
    assert spin_axis(taus[:1], spinning[:1], 0.3, 5.0) is None
