"""Which stored view of an object a new view is aligned to, and which views may become references."""

from __future__ import annotations

import math

import torch

from tivne.slam.objects.references import Reference, add_reference, centred_on, companions, comparable_view, pick_reference, shows_enough


def _camera_at(position) -> torch.Tensor:
    C = torch.eye(4, dtype=torch.float64)
    C[:3, 3] = torch.tensor(position, dtype=torch.float64)
    return C


def _reference(position, pixels=1000, tau=0.0) -> Reference:
    return Reference([], _camera_at(position), tau, pixels)


def _around(deg: float) -> tuple[float, float, float]:
    """A camera position on the unit circle about the object's z axis, ``deg`` from +x."""
    return (math.cos(math.radians(deg)), math.sin(math.radians(deg)), 0.0)


def test_companions_are_the_other_views_of_the_predicted_side_nearest_first():
    refs = [_reference(_around(a), tau=float(k)) for k, a in enumerate((0.0, 20.0, 5.0, 90.0, 10.0))]
    refs.append(_reference(tuple(2.0 * x for x in _around(3.0)), tau=5.0))  # the same side from twice as far
    C_pred = _camera_at(_around(4.0))
    ref = pick_reference(refs, C_pred, 12.0)
    assert ref.tau == 0.0
    # Within 24 degrees and 25 % of the distance, nearest in direction first, never the reference itself.
    assert [r.tau for r in companions(refs, ref, C_pred, 24.0, 4)] == [2.0, 4.0, 1.0]
    assert [r.tau for r in companions(refs, ref, C_pred, 24.0, 1)] == [2.0]
    assert companions(refs, ref, C_pred, 24.0, 0) == []


def test_stored_views_keep_covering_every_side_of_a_turning_object():
    # An object turning at 10 degrees per new view: past the limit the newer of the two views
    # nearest in direction goes, never the first; a second turn adds nothing new, so the first
    # turn's views (least drifted) are all kept, one per side.
    refs: list[Reference] = []
    for k in range(72):
        refs = add_reference(refs, _reference(_around(10.0 * k), tau=float(k)), 36)
    assert [r.tau for r in refs] == [float(k) for k in range(36)]
    # Fewer views than sides: the first stays, the kept ones spread over the sides seen (the oldest
    # N would leave all but the first 110 degrees, the newest N the first side, uncovered).
    few: list[Reference] = []
    for k in range(24):
        few = add_reference(few, _reference(_around(10.0 * k), tau=float(k)), 12)
    sides = sorted(round(math.degrees(math.atan2(float(r.C[1, 3]), float(r.C[0, 3])))) % 360 for r in few)
    assert len(few) == 12 and few[0].tau == 0.0 and sides[-1] >= 220
    assert max(b - a for a, b in zip(sides, sides[1:])) <= 30


def test_a_view_shows_enough_by_pixels_scaled_to_its_distance():
    ref = _reference((0.0, 0.0, 1.0), pixels=1000)
    assert shows_enough(1000, 1.0, ref)
    assert shows_enough(500, 1.0, ref)
    assert not shows_enough(499, 1.0, ref)  # occluded or cut by the border
    # Twice as far away an object covers a quarter of the pixels: 250 shows all of it, 100 does not.
    assert shows_enough(250, 2.0, ref)
    assert not shows_enough(100, 2.0, ref)


def test_the_oldest_reference_from_a_similar_view_is_picked_else_the_nearest_in_direction():
    refs = [_reference((0.0, 0.0, 1.0), tau=0.0), _reference((0.0, 1.0, 0.0), tau=1.0), _reference((1.0, 0.0, 0.0), tau=2.0)]
    assert pick_reference(refs, _camera_at((0.0, 0.05, 1.0)), 12.0).tau == 0.0  # near the first's direction
    # Same direction as the first but twice as far: no usable one; the nearest in direction is the first.
    assert pick_reference(refs, _camera_at((0.0, 0.0, 2.0)), 12.0).tau == 0.0
    # 17 degrees from the second's side (none within 12): the second, not the newest, which saw another side.
    assert pick_reference(refs, _camera_at((0.0, 1.0, 0.3)), 12.0).tau == 1.0
    # Opposite the newest, equally far from the other two: the newer of those.
    assert pick_reference(refs, _camera_at((-1.0, 0.0, 0.0)), 12.0).tau == 1.0


def test_a_pose_is_centred_where_the_origin_sat_behind_what_its_reference_saw():
    """The reference saw the object's near side, its centre 0.1 m in front of the origin towards the
    camera; now that side's centre is seen at (1, 2, 3.1): the origin goes 0.1 m behind it along the
    current camera's viewing direction, whatever the pose's rotation (kept as it is)."""
    ref = Reference([], _camera_at((0.0, 0.0, 1.0)), 0.0, 1000, torch.tensor([[0.0, 0.0, 0.1], [0.02, 0.0, 0.1], [-0.02, 0.0, 0.1]]))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # 90 deg about z
    centre = torch.tensor([1.0, 2.0, 3.1], dtype=torch.float64)
    centred = centred_on(T, ref, centre, torch.eye(3, dtype=torch.float64))
    assert torch.allclose(centred[:3, :3], T[:3, :3])
    assert torch.allclose(centred[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    R_wc = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)  # camera turned 90 deg about x
    assert torch.allclose(centred_on(T, ref, centre, R_wc)[:3, 3], torch.tensor([1.0, 2.1, 3.1], dtype=torch.float64))
    assert torch.equal(centred_on(T, _reference((0.0, 0.0, 1.0)), centre, R_wc), T)  # no points: unchanged
    # The object's middle 0.2 m from its origin along its x: the middle sits where the origin did, the
    # origin follows the pose's rotation (90 deg about z turns the object's x onto the world's y).
    middle = torch.tensor([0.2, 0.0, 0.0], dtype=torch.float64)
    ref_at_middle = Reference([], ref.C, 0.0, 1000, ref.points + middle.float())
    placed = centred_on(T, ref_at_middle, centre, torch.eye(3, dtype=torch.float64), middle)
    assert torch.allclose(placed[:3, 3] + T[:3, :3] @ middle, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    assert torch.allclose(placed[:3, 3], torch.tensor([1.0, 1.8, 3.0], dtype=torch.float64))


def test_an_object_seen_again_is_centred_on_the_stored_view_that_showed_as_much_of_it():
    """The oldest view of the side saw only the left half of the object's front (an occluder hid the
    rest), a later one all of it: a whole view now is centred on the whole one (the origin where it
    is), not on the half view, which would put the origin 7.5 cm off sideways (the front is 20 cm wide)."""
    half = torch.tensor([[x, y, 0.1] for x in (-0.1, -0.05) for y in (-0.05, 0.05)], dtype=torch.float32)
    whole = torch.tensor([[x, y, 0.1] for x in (-0.1, -0.05, 0.05, 0.1) for y in (-0.05, 0.05)], dtype=torch.float32)
    occluded = Reference([], _camera_at((0.0, 0.0, 1.0)), 0.0, 500, half)
    full = Reference([], _camera_at((0.0, 0.02, 1.0)), 1.0, 1000, whole)
    other_side = Reference([], _camera_at((1.0, 0.0, 0.0)), 2.0, 1100, whole)
    refs = [occluded, full, other_side]
    C_pred = _camera_at((0.0, 0.01, 1.0))
    assert pick_reference(refs, C_pred, 12.0) is occluded  # the alignment's choice: the oldest of the side
    assert comparable_view(refs, C_pred, 980, 12.0) is full
    assert comparable_view(refs, C_pred, 520, 12.0) is occluded  # half hidden now as well
    # No stored view from about that distance: pick_reference's choice.
    assert comparable_view(refs, _camera_at((0.0, 0.0, 2.0)), 250, 12.0) is pick_reference(refs, _camera_at((0.0, 0.0, 2.0)), 12.0)
    # Pixel counts are compared at one distance: a view from twice as far covers a quarter of them.
    far_refs = [Reference([], _camera_at((0.0, 0.0, 2.0)), 0.0, 130, half), Reference([], _camera_at((0.0, 0.0, 2.1)), 1.0, 250, whole)]
    assert comparable_view(far_refs, _camera_at((0.0, 0.0, 1.0)), 1000, 12.0) is pick_reference(far_refs, _camera_at((0.0, 0.0, 1.0)), 12.0)
    assert comparable_view(far_refs, _camera_at((0.0, 0.0, 2.05)), 240, 12.0).tau == 1.0
    centre = torch.tensor([0.0, 0.0, 2.9], dtype=torch.float64)  # the whole front's centre, seen now
    eye4, eye3 = torch.eye(4, dtype=torch.float64), torch.eye(3, dtype=torch.float64)
    right = centred_on(eye4, comparable_view(refs, C_pred, 980, 12.0), centre, eye3)
    wrong = centred_on(eye4, occluded, centre, eye3)
    assert torch.allclose(right[:3, 3], torch.tensor([0.0, 0.0, 2.8], dtype=torch.float64))
    assert abs(float(wrong[0, 3]) - 0.075) < 1e-6  # the half view puts it 7.5 cm off sideways
