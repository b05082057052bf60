"""Sensor model: every switch does what it says, and nothing else."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from data_modules.synthetic.sensor import (
    SensorModel,
    axial_sigma,
    blur_offsets,
    corrupt_depth,
    corrupt_rgb,
    exposure_gain,
    smear,
)

H, W = 120, 160
OFF = SensorModel(axial=0.0, edge_dropout=0.0, grazing_dropout=0.0, holes=0.0, dropout=0.0, rgb_noise=0.0)


def _step_scene() -> tuple[np.ndarray, np.ndarray]:
    """Depth 1.5 m on the left half, 3 m on the right (one vertical discontinuity); cos 0.05 in the
    bottom 20 rows (grazing), 0.9 elsewhere."""
    depth = np.full((H, W), 1.5)
    depth[:, W // 2 :] = 3.0
    cos = np.full((H, W), 0.9)
    cos[-20:] = 0.05
    return depth, cos


def test_all_parts_off_or_master_switch_off_is_exact():
    depth, cos = _step_scene()
    assert np.array_equal(corrupt_depth(depth, cos, OFF, 0, 0), depth)
    assert np.array_equal(corrupt_depth(depth, cos, SensorModel(depth_noise=False, lateral=1.0, quantization=0.01), 0, 0), depth)


def test_axial_noise_follows_sigma_z():
    depth, cos = _step_scene()
    for scale in (1.0, 2.5):
        z = corrupt_depth(depth, cos, replace(OFF, axial=scale), 3, 7)
        r = (z - depth) / axial_sigma(depth, scale)
        for half in (slice(0, W // 2), slice(W // 2, W)):
            assert abs(float(r[:, half].mean())) < 0.05 and 0.93 < float(r[:, half].std()) < 1.07
    assert axial_sigma(np.array([0.4]))[0] == pytest.approx(0.0012)


def test_quantization_gives_millimetre_steps():
    depth, cos = _step_scene()
    z = corrupt_depth(depth + 0.0004, cos, replace(OFF, axial=1.0, quantization=0.001), 0, 0)
    assert np.allclose(z * 1000, np.rint(z * 1000), atol=1e-9) and not np.array_equal(z, depth)


def test_edge_and_grazing_dropout_stay_where_they_belong():
    depth, cos = _step_scene()
    edges = corrupt_depth(depth, cos, replace(OFF, edge_dropout=0.6), 0, 0) == 0
    cols = np.flatnonzero(edges.any(0))
    assert cols.min() >= W // 2 - 2 and cols.max() <= W // 2 + 1  # a band around the discontinuity
    assert 0.4 < edges[:, W // 2 - 1 : W // 2 + 1].mean() < 0.8
    grazing = corrupt_depth(depth, cos, replace(OFF, grazing_dropout=0.5), 0, 0) == 0
    assert not grazing[:-20].any() and 0.4 < grazing[-20:].mean() < 0.6


def test_holes_and_dropout_rates():
    depth, cos = _step_scene()
    sparse = corrupt_depth(depth, cos, replace(OFF, dropout=0.02), 0, 0) == 0
    assert 0.015 < sparse.mean() < 0.025
    counts = [int((corrupt_depth(depth, cos, replace(OFF, holes=4.0), 0, i) == 0).any()) for i in range(20)]
    assert 15 <= sum(counts)  # P(no hole) = e^-4 per frame
    blobs = corrupt_depth(depth, cos, replace(OFF, holes=20.0), 0, 1) == 0
    assert 0.01 < blobs.mean() < 0.5


def test_lateral_jitter_ragged_edges_flat_interiors():
    depth, cos = _step_scene()
    z = corrupt_depth(depth, cos, replace(OFF, lateral=1.0), 0, 0)
    changed = z != depth
    cols = np.flatnonzero(changed.any(0))
    assert changed.any() and cols.min() >= W // 2 - 3 and cols.max() <= W // 2 + 2  # only within 3 sigma of the edge
    assert set(np.unique(z)) == {1.5, 3.0}  # values move sideways, never blend


def test_parts_draw_independent_streams():
    depth, cos = _step_scene()
    axial = replace(OFF, axial=1.0)
    a = corrupt_depth(depth, cos, axial, 5, 2)
    b = corrupt_depth(depth, cos, replace(axial, dropout=0.1), 5, 2)
    kept = b > 0
    assert np.array_equal(a[kept], b[kept])  # switching dropout on leaves the axial noise unchanged
    assert not np.array_equal(a, corrupt_depth(depth, cos, axial, 6, 2))  # the seed selects the realisation
    assert not np.array_equal(a, corrupt_depth(depth, cos, axial, 5, 3))  # ... and so does the frame


def test_colour_noise_exposure_and_quantisation():
    rgb = torch.full((H, W, 3), 0.5)
    clean = corrupt_rgb(rgb, 0.0, OFF, 0, 0)
    assert clean.dtype == torch.uint8 and bool((clean == 128).all())
    noisy = corrupt_rgb(rgb, 0.0, replace(OFF, rgb_noise=0.02), 0, 0).float() / 255
    assert 0.018 < float(noisy.std()) < 0.022
    gains = [exposure_gain(t, replace(OFF, exposure=0.15), 0) for t in np.arange(0, 6, 1 / 30)]
    assert max(gains) > 1.05 and min(gains) < 0.95 and max(np.abs(np.diff(gains))) < 0.02  # a smooth drift
    assert exposure_gain(1.0, OFF, 0) == 1.0
    bright = corrupt_rgb(rgb, 0.0, replace(OFF, exposure=0.15), 0, 0).float() / 255
    assert float(bright.mean()) == pytest.approx(0.5 * exposure_gain(0.0, replace(OFF, exposure=0.15), 0), abs=2 / 255)


def test_blur_offsets_span_the_shutter():
    assert blur_offsets(OFF, 30.0) == [] and blur_offsets(replace(OFF, motion_blur=1), 30.0) == []
    off = blur_offsets(replace(OFF, motion_blur=4, shutter=0.6), 30.0)
    assert len(off) == 4 and sum(off) == pytest.approx(0.0) and off[-1] - off[0] == pytest.approx(0.6 / 30 * 3 / 4)


def test_smear_averages_backward_warps():
    rgb = torch.rand(H, W, 3)
    assert torch.allclose(smear(rgb, [torch.zeros(H, W, 2)] * 3), rgb, atol=1e-4)
    shift = torch.zeros(H, W, 2)
    shift[..., 0] = 2.0  # the content moves 2 px right: pixel x shows what was at x - 2
    out = smear(rgb, [torch.zeros(H, W, 2), shift])
    assert torch.allclose(out[:, 2:], (rgb[:, 2:] + rgb[:, :-2]) / 2, atol=1e-4)  # grid_sample rounding


def test_problems_name_the_field():
    assert SensorModel().problems() == []
    bad = SensorModel(axial=-1.0, dropout=1.5, motion_blur=2.5, rgb_noise=float("nan"), depth_noise="yes", blur_exact=1)  # type: ignore[arg-type]
    assert {k for k, _ in bad.problems()} == {"axial", "dropout", "motion_blur", "rgb_noise", "depth_noise", "blur_exact"}
    assert not math.isnan(SensorModel().shutter)
