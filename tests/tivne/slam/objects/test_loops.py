"""Loop closure along an object's chain of reference views: when it is one, and how its drift is spread."""

from __future__ import annotations

import math

import torch

from tivne.geometry import invert_pose, pose_difference
from tivne.slam.objects.loops import chain_share, closes_loop, spread_drift
from tivne.slam.objects.references import Reference
from tivne.slam.objects.track import ObjectTrack


def _turn_z(deg: float, shift=(0.0, 0.0, 0.0)) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T = torch.eye(4, dtype=torch.float64)
    T[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    T[:3, 3] = torch.tensor(shift, dtype=torch.float64)
    return T


def _views(taus) -> list[Reference]:
    return [Reference([], _turn_z(30.0 * k), float(t), 100, torch.ones(5, 3, dtype=torch.float64)) for k, t in enumerate(taus)]


def test_a_loop_is_an_older_view_at_least_two_stored_views_up_the_chain():
    refs = _views([0.0, 1.0, 2.0, 3.0])
    assert closes_loop(refs, refs[0], refs[3]) and closes_loop(refs, refs[1], refs[3])
    assert not closes_loop(refs, refs[2], refs[3])  # a neighbour: the joint alignment reconciles it
    assert not closes_loop(refs, refs[3], refs[0])  # a newer view is the chain going on
    assert not closes_loop(refs, refs[0], refs[0]) and not closes_loop(refs, refs[0], None)
    evicted = Reference([], torch.eye(4, dtype=torch.float64), 2.5)  # the chain's view, dropped from the store since
    assert closes_loop(refs, refs[1], evicted) and not closes_loop(refs, refs[2], evicted)


def test_chain_share_runs_from_the_old_view_to_the_reached_one():
    assert [chain_share(t, 1.0, 3.0) for t in (0.5, 1.0, 2.0, 3.0, 4.0)] == [0.0, 0.0, 0.5, 1.0, 1.0]


def test_the_drift_is_spread_along_the_chain_and_fully_on_what_came_after():
    """A 4° spin drift closed between the views at τ 0 and 2: the view halfway turns by 2°, the
    reached one and the later poses by all 4°, the old view not at all; the track's poses follow
    their camera-to-object views (T_wo ← T_wo · L^-w keeps T_wo⁻¹ T_wc = C turning with them)."""
    refs = _views([0.0, 1.0, 2.0])
    before = [r.C.clone() for r in refs]
    track = ObjectTrack(1)
    poses = {tau: _turn_z(10.0 * tau, (0.1 * tau, 0.0, 0.0)) for tau in (0.0, 1.0, 2.0, 2.5)}
    for tau, pose in poses.items():
        track.add(tau, pose)
    L = _turn_z(4.0, (0.002, 0.0, 0.0))
    spread_drift(L, refs, track, 0.0, 2.0)
    turned = [pose_difference(b, r.C)[1] for b, r in zip(before, refs)]
    assert turned[0] == 0.0 and math.isclose(turned[1], 2.0, abs_tol=1e-9) and math.isclose(turned[2], 4.0, abs_tol=1e-9)
    assert torch.allclose(refs[2].C, L @ before[2], atol=1e-12)
    assert torch.allclose(refs[2].points, (L[:3, :3] @ torch.ones(5, 3, dtype=torch.float64).T).T + L[:3, 3], atol=1e-12)
    after = dict(zip(track.observed_taus(), track.poses()))
    assert torch.equal(after[0.0], poses[0.0])
    for tau in (2.0, 2.5):
        assert torch.allclose(after[tau], poses[tau] @ invert_pose(L), atol=1e-12)
    assert math.isclose(pose_difference(poses[1.0], after[1.0])[1], 2.0, abs_tol=1e-9)


def _chain_with_loop(monkeypatch, drifts):
    """Four stored views and a track at τ 0..3; chain_drift answers ``drifts`` in turn."""
    import tivne.slam.objects.loops as loops

    answers = iter(drifts)
    monkeypatch.setattr(loops, "chain_drift", lambda *args, **kwargs: next(answers))
    refs = _views([0.0, 1.0, 2.0, 3.0])
    track = ObjectTrack(1)
    for tau in (0.0, 1.0, 2.0, 3.0):
        track.add(tau, _turn_z(10.0 * tau))
    return loops.ChainLoops(), refs, track


def _step(loops, refs, track, picked, reached, tau):
    return loops.step(1, refs, track, picked, reached, tau, None, None, float("nan"))


def test_a_loop_is_closed_only_when_the_next_view_repeats_its_drift(monkeypatch):
    loops, refs, track = _chain_with_loop(monkeypatch, [_turn_z(3.0), _turn_z(3.4)])
    before = track.poses().clone()
    assert not _step(loops, refs, track, refs[0], refs[3], 4.0)  # seen on one view: nothing moves yet
    assert torch.equal(track.poses(), before) and loops.metrics()["object_loops_closed"] == 0
    track.add(4.0, _turn_z(40.0))  # that view's pose, measured against the old view
    assert _step(loops, refs, track, refs[1], refs[0], 5.0)
    m = loops.metrics()
    assert m["object_loops_closed"] == 1 and m["object_loops_refused"] == 0
    assert math.isclose(m["object_loop_largest_deg"], 3.2, abs_tol=1e-9)  # the mean of both views' drifts
    after = track.poses()
    turned = [pose_difference(a, b)[1] for a, b in zip(before, after[:4])]
    assert turned[0] == 0.0 and math.isclose(turned[3], 3.2, abs_tol=1e-9) and math.isclose(turned[1], 3.2 / 3, abs_tol=1e-9)
    assert torch.equal(after[4], _turn_z(40.0))  # from the view that saw the loop on: measured against the old view


def test_a_loop_the_next_view_does_not_repeat_is_refused(monkeypatch):
    loops, refs, track = _chain_with_loop(monkeypatch, [_turn_z(3.0), _turn_z(6.0), _turn_z(3.0), None])
    before = track.poses().clone()
    assert not _step(loops, refs, track, refs[0], refs[3], 4.0)
    track.add(4.0, _turn_z(40.0))
    assert not _step(loops, refs, track, refs[1], refs[0], 5.0)  # 3° apart: a lock onto smeared texture
    assert torch.equal(track.poses()[:4], before) and loops.metrics()["object_loops_refused"] == 1
    assert not _step(loops, refs, track, refs[0], refs[3], 6.0)  # seen again, but that view was not taken
    assert not _step(loops, refs, track, refs[1], refs[0], 7.0)
    assert loops.metrics()["object_loops_closed"] == 0
