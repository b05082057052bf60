"""Seeded layout: rooms, shapes, and furniture that keeps clear of walls, each other and keep-out zones."""

from __future__ import annotations

import numpy as np
import pytest

from data_modules.synthetic.layout import footprint_radius, random_furniture, random_room, random_shape, swept_xy
from data_modules.synthetic.motion import Orbit
from data_modules.synthetic.shapes import Box, Cylinder, Sphere, bound_half


def test_room_and_shapes_are_seeded_and_in_range():
    room = random_room(np.random.default_rng(0))
    assert room == random_room(np.random.default_rng(0)) and room != random_room(np.random.default_rng(1))
    assert 2.3 <= room.hi[0] <= 3.0 and room.lo[0] == -room.hi[0] and room.lo[2] == 0.0 and len(room.textures) == 6
    kinds = {type(random_shape(np.random.default_rng(s), 0.2)) for s in range(30)}
    assert kinds == {Box, Cylinder, Sphere}
    assert all(float(np.max(bound_half(random_shape(np.random.default_rng(s), 0.2)))) <= 0.2 * 1.2 + 1e-9 for s in range(30))
    with pytest.raises(ValueError):
        random_shape(np.random.default_rng(0), 0.2, ("cone",))


def test_furniture_stands_clear():
    rng = np.random.default_rng(4)
    room = random_room(rng)
    orbit = Orbit((0.0, 0.0, 0.3), 0.8, 1.0)
    keep = [(swept_xy(orbit.pose, 10.0), 0.3)]
    pieces = random_furniture(rng, room, 8, keep)
    assert 4 <= len(pieces) <= 8
    xy = np.array([p.motion.pose(0.0)[:2, 3] for p in pieces])
    r = np.array([footprint_radius(p.shape) for p in pieces])
    for k, piece in enumerate(pieces):
        T = piece.motion.pose(0.0)
        assert T[2, 3] == pytest.approx(float(bound_half(piece.shape)[2]))  # standing on the floor
        assert (xy[k] - r[k] >= np.array(room.lo[:2])).all() and (xy[k] + r[k] <= np.array(room.hi[:2])).all()
        assert np.min(np.linalg.norm(keep[0][0] - xy[k], axis=1)) > r[k] + 0.3
        others = np.delete(np.arange(len(pieces)), k)
        assert (np.linalg.norm(xy[others] - xy[k], axis=1) > r[others] + r[k]).all()
    assert len({p.name for p in pieces}) == len(pieces)
