"""Which stored view of an object a new view is aligned to, and which views may become references."""

from __future__ import annotations

import torch

from tivne.slam.objects.references import Reference, pick_reference, shows_enough


def _camera_at(position) -> torch.Tensor:
    C = torch.eye(4, dtype=torch.float64)
    C[:3, 3] = torch.tensor(position, dtype=torch.float64)
    return C


def _reference(position, pixels=1000, tau=0.0) -> Reference:
    return Reference([], _camera_at(position), tau, pixels)


def test_a_view_shows_enough_by_pixels_scaled_to_its_distance():
    ref = _reference((0.0, 0.0, 1.0), pixels=1000)
    assert shows_enough(1000, 1.0, ref)
    assert shows_enough(500, 1.0, ref)
    assert not shows_enough(499, 1.0, ref)  # occluded or cut by the border
    # Twice as far away an object covers a quarter of the pixels: 250 shows all of it, 100 does not.
    assert shows_enough(250, 2.0, ref)
    assert not shows_enough(100, 2.0, ref)


def test_the_oldest_reference_from_a_similar_view_is_picked_else_the_newest():
    refs = [_reference((0.0, 0.0, 1.0), tau=0.0), _reference((0.0, 1.0, 0.0), tau=1.0), _reference((1.0, 0.0, 0.0), tau=2.0)]
    assert pick_reference(refs, _camera_at((0.0, 0.05, 1.0)), 12.0).tau == 0.0  # near the first's direction
    assert pick_reference(refs, _camera_at((0.0, 0.0, 2.0)), 12.0).tau == 2.0  # same direction, twice as far
    assert pick_reference(refs, _camera_at((-1.0, 0.0, 0.0)), 12.0).tau == 2.0  # no stored view near it
