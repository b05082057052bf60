"""Seeds -> objects (tivne.masks.segments): depth segments and the mask clean-up."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from tivne.masks.segments import clean_mask, depth_segments

sys.path.insert(0, str(Path(__file__).parent))
from mask_scenes import H, W, scene_depth, square  # noqa: E402


def test_depth_segments_split_object_from_background():
    obj = square(10, 10, 12)
    labels, n = depth_segments(scene_depth(obj).numpy())
    assert n == 2
    inner = labels[obj.numpy()]
    assert len(set(inner[inner > 0].tolist())) == 1


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
