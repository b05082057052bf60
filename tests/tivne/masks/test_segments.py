"""Seeds -> objects (tivne.masks.segments): depth segments and the mask clean-up."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from data_modules.sensor import kinect_depth_sigma
from tivne.masks.segments import clean_mask, closing, concave_creases, depth_segments, opening

sys.path.insert(0, str(Path(__file__).parent))
from mask_scenes import H, W, scene_depth, square  # noqa: E402


def test_depth_segments_split_object_from_background():
    obj = square(10, 10, 12)
    labels, n = depth_segments(scene_depth(obj).numpy())
    assert n == 2
    inner = labels[obj.numpy()]
    assert len(set(inner[inner > 0].tolist())) == 1


def test_holes_cut_a_small_object_s_rim_only_where_asked():
    # A sensor shadow (no depth) along three sides of a 5x5 object. As a near side of a jump (hole_edges, the
    # objects' own pixels) it cuts the object's rim off, 13 of 25 pixels left; without, all 25 stay one segment
    # apart from the wall, and the motion mask (clean_mask) keeps the whole object.
    obj = square(10, 10, 5)
    depth = scene_depth(obj).numpy()
    shadow = np.zeros_like(depth, dtype=bool)
    shadow[9, 9:16] = shadow[10:15, 9] = shadow[15, 10:14] = True
    depth[shadow] = 0.0
    cut, _ = depth_segments(depth)
    assert int((cut[obj.numpy()] > 0).sum()) == 13
    labels, _ = depth_segments(depth, hole_edges=False)
    inner = labels[obj.numpy()]
    assert (inner > 0).all() and len(set(inner.tolist())) == 1
    assert not np.isin(labels[~obj.numpy() & ~shadow], inner).any()
    assert clean_mask(obj.numpy().copy(), depth, min_area=20)[obj.numpy()].all()


def test_clean_mask_grows_seeds_drops_speckle_and_keeps_temporal():
    obj = square(10, 10, 14)
    depth = scene_depth(obj).numpy()
    seeds = np.zeros((H, W), bool)
    seeds[10:24, 20:24] = True  # a 4-px leading-edge strip of the object
    seeds[40, 50] = seeds[5, 55] = True  # speckle on the background
    out = clean_mask(seeds, depth)
    assert (out == obj.numpy()).mean() > 0.99 and out[obj.numpy()].all()
    # No seeds this frame: the object survives through the previous frame's mask, only then.
    none = np.zeros_like(seeds)
    assert not clean_mask(none, depth).any()
    assert clean_mask(none, depth, previous=obj.numpy()).sum() == obj.sum()
    # A segment covering most of the frame (the background) is never dynamic.
    assert not clean_mask(np.ones_like(seeds), scene_depth(None).numpy()).any()


def test_clean_mask_keeps_the_pixels_where_the_image_border_cuts_an_object():
    # The object tracker reads "cut off by the view" from a mask reaching the border; the closing took
    # the border column (scipy's 0 border), so every geometric mask stopped a stride short of it.
    obj = square(10, W - 12, 14)  # 14 wide from 12 columns before the edge: the image cuts its last 2
    depth = scene_depth(obj).numpy()
    seeds = obj.numpy().copy()
    seeds[:, W - 1] = False  # the edge itself not flagged: the opening, closing and edge growth give it back
    for close_radius in (1, 2):
        out = clean_mask(seeds, depth, close_radius=close_radius)
        assert np.array_equal(out, obj.numpy())
    assert clean_mask(obj.numpy().copy(), depth)[:, W - 1].any()


def test_opening_and_closing_are_scipy_s_inside_and_take_nothing_from_the_image_edge():
    from scipy import ndimage

    rng = np.random.default_rng(0)
    mask = rng.random((30, 40)) < 0.55
    window = np.ones((3, 3), bool)
    inside = (slice(2, -2), slice(2, -2))
    assert np.array_equal(opening(mask, 1)[inside], ndimage.binary_opening(mask, window)[inside])
    assert np.array_equal(closing(mask, 1)[inside], ndimage.binary_closing(mask, window)[inside])
    full = np.ones((30, 40), bool)
    assert opening(full, 1).all() and closing(full, 1).all()


def test_clean_mask_segment_score_catches_slow_motion_but_not_a_pose_error():
    moving, still = square(8, 8, 12), square(30, 40, 10)  # two objects in front of the background
    depth = scene_depth(moving | still).numpy()
    rng = np.random.default_rng(0)
    noise = np.abs(rng.normal(size=(H, W)))  # |residual| / σ of a static scene: median ~0.67
    none = np.zeros((H, W), bool)
    slow = np.where(moving.numpy(), 4.0 + noise, noise)  # 4σ on the object: no single pixel seeds
    out = clean_mask(none, depth, motion_score=slow, min_area=4)
    assert (out == moving.numpy()).mean() > 0.99 and not out[still.numpy()].any()
    assert not clean_mask(none, depth, motion_score=slow, min_area=4, score_threshold=6.0).any()
    # A pose error moves everything, the still object too: the background's own score raises the bar.
    pose_error = noise + 3.5
    assert not clean_mask(none, depth, motion_score=pose_error, min_area=4).any()
    # Unknown residuals (NaN) do not count; a segment mostly unknown is not judged.
    unknown = np.where(moving.numpy(), np.nan, slow)
    assert not clean_mask(none, depth, motion_score=unknown, min_area=4).any()


# A 80x60 pinhole camera looking along +z, y down: a floor 0.8 m below it, a wall at 4 m and a door
# (a vertical plane at 2 m, 1 m wide, 1.2 m tall) standing on the floor.
F, CX, CY, FLOOR, WALL, DOOR = 60.0, 39.5, 29.5, 0.8, 4.0, 2.0


def _rays(w: int = 80, h: int = 60) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return (u - CX) / F, (v - CY) / F


def door_on_floor() -> tuple[np.ndarray, np.ndarray]:
    """(60, 80) depth of the room and the door's (60, 80) bool mask."""
    x, y = _rays()
    floor = np.where(y > 0, FLOOR / np.maximum(y, 1e-9), np.inf)
    depth = np.minimum(floor, WALL)
    door = (np.abs(x * DOOR) <= 0.5) & (y * DOOR >= FLOOR - 1.2) & (DOOR <= depth)
    depth[door] = DOOR
    return depth, door


def test_concave_creases_mark_where_a_door_meets_the_floor_but_not_planes_or_convex_edges():
    depth, door = door_on_floor()
    crease = concave_creases(depth, 3.0)
    contact = int(np.ceil(CY + F * FLOOR / DOOR))  # the first floor row in front of the door
    rows = np.nonzero(crease[20:, 40])[0] + 20  # below the door's top (the far side of a depth jump is marked too)
    assert len(rows) and np.abs(rows - contact).max() <= 2
    inside = door.copy()
    inside[contact - 3 :] = False
    assert not crease[inside].any()  # the door's own plane
    assert not crease[contact + 4 :].any()  # the floor in front of it, slanted as it is
    # A ridge pointing at the camera (a box's vertical edge) is convex, a valley (a room's corner) concave.
    x, _ = _rays()
    left, right = DOOR / (1 - 0.8 * x), DOOR / (1 + 0.8 * x)  # planes z = D ± 0.8 x through the line x = 0, z = D
    assert not concave_creases(np.maximum(left, right), 3.0).any()
    valley = concave_creases(np.minimum(left, right), 3.0)
    assert valley.any() and (np.abs(np.nonzero(valley)[1] - CX) <= 2.5).all()
    # Sensor noise on a slanted plane: hardly a crease.
    rng = np.random.default_rng(0)
    noisy = depth + rng.normal(size=depth.shape) * kinect_depth_sigma(depth)
    assert concave_creases(noisy, 3.0)[contact + 4 :].mean() < 0.01


def test_creases_cut_a_door_off_the_room_so_its_seeds_make_it_dynamic():
    depth, door = door_on_floor()
    labels, _ = depth_segments(depth)
    assert labels[door & (labels > 0)].max() == labels[-1, 40]  # door, floor and wall: one segment
    labels, _ = depth_segments(depth, crease_sigmas=3.0)
    on_door = np.unique(labels[door & (labels > 0)])
    assert len(on_door) == 1 and not (labels[~door] == on_door[0]).any()
    seeds = np.zeros_like(door)
    seeds[door & (np.arange(80)[None, :] > 40)] = True  # the swinging half of the door
    assert not clean_mask(seeds, depth, min_area=4).any()  # part of the background
    out = clean_mask(seeds, depth, min_area=4, crease_sigmas=3.0)
    assert (out & door).sum() >= 0.9 * door.sum() and (out & ~door).sum() <= 0.05 * door.sum()
