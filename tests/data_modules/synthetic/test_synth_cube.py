"""The ``cube`` preset: today's moving-cube scene reproduced (stored reference renders of the original
``MovingCubeSequence``), exact geometry, masks, noise, determinism and the frame cache."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError
from data_modules.synthetic import SyntheticSequence
from tivne.geometry import invert_pose, pixel_grid, pixel_to_ray, project, transform_points

CUBE_HALF = 0.18
ROOM_MIN, ROOM_MAX = (-2.0, -1.5, 0.0), (2.0, 1.5, 2.6)
REFERENCE = json.loads((Path(__file__).parent / "cube_reference.json").read_text())


def MovingCubeSequence(**kwargs) -> SyntheticSequence:  # the original class: its name and defaults, scene=cube
    return SyntheticSequence(**{"scene": "cube", **kwargs})


@pytest.mark.parametrize("case", REFERENCE["cases"], ids=lambda c: f"{c['width']}x{c['height']}-f{c['frame']}")
def test_matches_the_original_moving_cube_renders(case):
    """Noise-free frames equal the original class's: depth to 1e-6 m, colour to one 8-bit level, same mask."""
    ds = MovingCubeSequence(num_frames=case["num_frames"], fps=case["fps"], width=case["width"], height=case["height"])
    f = ds.render(case["frame"], noise=False)
    rows, cols = torch.tensor(case["rows"]), torch.tensor(case["cols"])
    depth = f.depth.double()[rows[:, None], cols[None, :]]
    assert torch.allclose(depth, torch.tensor(case["depth"], dtype=torch.float64), atol=1e-6, rtol=0)
    rgb8 = (f.rgb * 255).round().long()[rows[:, None], cols[None, :]]
    assert int((rgb8 - torch.tensor(case["rgb8"])).abs().max()) <= 1
    assert float(f.depth.double().mean()) == pytest.approx(case["depth_mean"], abs=1e-6)
    assert np.allclose((f.rgb * 255).round().reshape(-1, 3).mean(0).numpy(), case["rgb_mean"], atol=0.01)
    vv, uu = torch.nonzero(f.mask, as_tuple=True)
    assert int(f.mask.sum()) == case["mask_pixels"]
    assert [int(vv.min()), int(vv.max()), int(uu.min()), int(uu.max())] == case["mask_box"]
    assert torch.allclose(f.gt_pose, torch.tensor(case["pose"], dtype=torch.float64), atol=1e-11)


def _world_rays(ds: SyntheticSequence, i: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera centre (3,) and (H, W, 3) world ray directions with camera z = 1 for frame i."""
    K = ds.intrinsics.K(dtype=torch.float64)
    d_cam = pixel_to_ray(pixel_grid(ds.height, ds.width, dtype=torch.float64), K)
    T = ds.camera_pose(i)
    return T[:3, 3], d_cam @ T[:3, :3].T


def _sigma(z):
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def test_frames_intrinsics_and_timestamps(tiny_cube):
    ds = tiny_cube
    assert len(ds) == 6 and ds.name == "cube" and ds.has_gt_poses and ds.has_masks
    K = ds.intrinsics
    assert (K.fx, K.fy, K.cx, K.cy, K.width, K.height) == (64.0, 64.0, 39.5, 29.5, 80, 60)
    assert np.allclose(ds.timestamps, np.arange(6) / 30.0)
    for i in range(len(ds)):
        f = ds[i]
        f.validate("test", ds.intrinsics)
        assert f.index == i and f.timestamp == pytest.approx(i / 30.0)
        assert f.gt_pose.dtype == torch.float64 and torch.equal(f.gt_pose, ds.camera_pose(i))
        assert f.mask.dtype == torch.bool and f.mask.any()
        assert (f.depth > 0).all()  # noise-free: every pixel sees a surface
    with pytest.raises(IndexError):
        ds[6]


@pytest.mark.parametrize(
    "kwargs, param",
    [
        ({"num_frames": 0}, "num_frames"),
        ({"fps": 0.0}, "fps"),
        ({"num_frames": 2.5}, "num_frames"),
        ({"width": "wide"}, "width"),
        ({"fps": -30.0}, "fps"),
        ({"fps": float("nan")}, "fps"),
        ({"width": 4}, "width"),
        ({"height": 2}, "height"),
        ({"seed": -1}, "seed"),
        ({"camera_speed": float("inf")}, "camera_speed"),
        ({"rgb_noise": -0.1}, "rgb_noise"),
        ({"scene": "kitchen"}, "scene"),
        ({"sensor": {"axial": -1.0}}, "sensor.axial"),
        ({"sensor": {"blur": 3}}, "sensor.blur"),
        ({"depth_noise": "yes"}, "depth_noise"),
    ],
)
def test_bad_kwargs_raise_dataset_error(kwargs, param):
    with pytest.raises(DatasetError, match=param):
        MovingCubeSequence(**kwargs)


def test_room_planes_depth_is_analytic():
    """Noise-free depth of the floor and the far wall equals the analytic ray/plane z-depth."""
    ds = MovingCubeSequence(num_frames=40, width=160, height=120, depth_noise=False, rgb_noise=0.0)
    for i in (0, 39):
        depth = ds[i].depth.double()
        o, d = _world_rays(ds, i)
        for axis, value in ((2, ROOM_MIN[2]), (1, ROOM_MAX[1])):  # floor z = 0, far wall y = 1.5
            t = (value - o[axis]) / d[..., axis]
            hit = o + t[..., None] * d
            inside = torch.ones_like(t, dtype=torch.bool)
            for a in range(3):
                if a != axis:
                    inside &= (hit[..., a] > ROOM_MIN[a]) & (hit[..., a] < ROOM_MAX[a])
            candidates = inside & (t > 0)
            exact = candidates & ((depth - t).abs() < 1e-4)
            assert exact.sum() > 0.4 * candidates.sum() > 0
            # Every other candidate is occluded: the rendered depth is nearer and lies on a real surface.
            other = candidates & ~exact
            assert bool((depth[other] < t[other]).all())
            on_surface = ds.sdf(o + depth[other][:, None] * d[other], ds.timestamps[i])
            assert float(on_surface.abs().max()) < 1e-5


def test_depth_lies_on_surfaces_and_path_is_free(tiny_cube):
    ds = tiny_cube
    for i in (0, 5):
        f = ds[i]
        t = f.timestamp
        o, d = _world_rays(ds, i)
        z = f.depth.double()
        pts = (o + z[..., None] * d).reshape(-1, 3)
        assert float(ds.sdf(pts, t).abs().max()) < 1e-5
        for frac in (0.2, 0.5, 0.8, 0.97):
            mid = (o + frac * z[..., None] * d).reshape(-1, 3)
            assert bool((ds.sdf(mid, t) > 0).all())  # nothing in front of the first hit


def test_mask_is_first_hit_of_cube(tiny_cube):
    ds = tiny_cube
    for i in (0, 3, 5):
        f = ds[i]
        c, h, R = ds.dynamic_box(f.timestamp)
        assert torch.allclose(h, torch.full((3,), CUBE_HALF, dtype=torch.float64))
        o, d = _world_rays(ds, i)
        # Independent slab test in the cube's frame.
        ol = (o - c) @ R
        dl = d @ R
        t1, t2 = (-h - ol) / dl, (h - ol) / dl
        tnear = torch.minimum(t1, t2).max(-1).values
        tfar = torch.maximum(t1, t2).min(-1).values
        hits_cube = (tnear <= tfar) & (tnear > 0)
        first = hits_cube & (tnear <= f.depth.double() + 1e-6)
        assert torch.equal(first, f.mask)
        # The mask lies inside the bounding box of the projected cube corners.
        signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)
        corners = c + (signs * h) @ R.T
        uv, zc = project(transform_points(invert_pose(f.gt_pose), corners), ds.intrinsics.K(dtype=torch.float64))
        assert (zc > 0).all()
        vv, uu = torch.nonzero(f.mask, as_tuple=True)
        assert uu.min() >= uv[:, 0].min() - 0.5 and uu.max() <= uv[:, 0].max() + 0.5
        assert vv.min() >= uv[:, 1].min() - 0.5 and vv.max() <= uv[:, 1].max() + 0.5


def test_static_points_agree_between_frames():
    """Static points of frame A, moved into frame B with GT poses, match B's depth to < 1 mm."""
    ds = MovingCubeSequence(num_frames=20, width=160, height=120, depth_noise=False, rgb_noise=0.0)
    a, b = ds[0], ds[19]
    K = ds.intrinsics.K(dtype=torch.float64)
    uv = pixel_grid(ds.height, ds.width, dtype=torch.float64)
    pa = (pixel_to_ray(uv, K) * a.depth.double()[..., None])[~a.mask]
    pb = transform_points(invert_pose(b.gt_pose) @ a.gt_pose, pa)
    uvb, zb = project(pb, K)
    u0, v0 = uvb[:, 0].floor().long(), uvb[:, 1].floor().long()
    ok = (u0 >= 0) & (v0 >= 0) & (u0 < ds.width - 1) & (v0 < ds.height - 1)
    u0, v0, fu, fv, zb = u0[ok], v0[ok], (uvb[ok, 0] - u0[ok]), (uvb[ok, 1] - v0[ok]), zb[ok]
    inv = 1.0 / b.depth.double()
    q00, q01, q10, q11 = inv[v0, u0], inv[v0, u0 + 1], inv[v0 + 1, u0], inv[v0 + 1, u0 + 1]
    # 1/z is affine in (u, v) on a plane: keep 2x2 neighbourhoods on one planar, static face.
    static = ~(b.mask[v0, u0] | b.mask[v0, u0 + 1] | b.mask[v0 + 1, u0] | b.mask[v0 + 1, u0 + 1])
    planar = (q00 + q11 - q01 - q10).abs() < 2e-6  # float32 depth rounding
    interp = 1.0 / ((q00 * (1 - fu) + q01 * fu) * (1 - fv) + (q10 * (1 - fu) + q11 * fu) * fv)
    visible = static & planar & ((interp - zb).abs() < 0.05)
    assert visible.sum() > 0.5 * ok.sum()
    assert float((interp - zb)[visible].abs().max()) < 1e-3


@pytest.mark.parametrize("part", ["all", "static", "dynamic"])
def test_sample_surface_is_on_zero_level_set(tiny_cube, part):
    ds = tiny_cube
    t = 0.1
    pts = ds.sample_surface(t, 3000, part=part, seed=1)
    assert pts.shape == (3000, 3) and pts.dtype == torch.float64
    assert float(ds.sdf(pts, t).abs().max()) < 1e-6
    assert torch.equal(pts, ds.sample_surface(t, 3000, part=part, seed=1))
    c, h, R = ds.dynamic_box(t)
    on_cube = ((pts - c) @ R).abs().max(-1).values <= CUBE_HALF + 1e-9
    if part == "dynamic":
        assert on_cube.all()
        # Uniform over the 6 equal faces.
        face = ((pts - c) @ R).abs().argmax(-1)
        assert torch.bincount(face, minlength=3).float().div(3000).sub(1 / 3).abs().max() < 0.05
    elif part == "static":
        assert not on_cube.any()
    else:
        assert 0 < on_cube.float().mean() < 0.05  # the cube is a small share of the total area
    if part != "dynamic":
        floor = pts[pts[:, 2].abs() < 1e-9]
        assert len(floor) > 100
        # No floor samples under box A (centre (-1.05, 0.75), hidden by the box).
        assert not ((floor[:, :2] - torch.tensor([-1.05, 0.75], dtype=torch.float64)).norm(dim=-1) < 0.2).any()


def test_sdf_signs(tiny_cube):
    ds = tiny_cube
    c, h, _ = ds.dynamic_box(0.0)
    pts = torch.stack([ds.camera_pose(0)[:3, 3], c, torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)])
    s = ds.sdf(pts, 0.0)
    assert s[0] > 0.2
    assert s[1] == pytest.approx(-CUBE_HALF)
    assert s[2] == pytest.approx(-0.4)  # 0.4 m above the ceiling
    assert torch.equal(ds.sdf(pts[1:2], 0.0, part="dynamic"), s[1:2])
    assert ds.sdf(pts[1:2], 0.0, part="static")[0] > 0


def test_motion_magnitudes():
    ds = MovingCubeSequence(num_frames=150, width=16, height=16)
    P = ds.camera_poses()
    rel = invert_pose(P[:-1]) @ P[1:]
    step = rel[:, :3, 3].norm(dim=-1)
    angle = torch.rad2deg(torch.acos(((rel.diagonal(dim1=-2, dim2=-1)[:, :3].sum(-1) - 1) / 2).clamp(-1, 1)))
    assert 0.005 < float(step.mean()) < 0.015 and float(step.max()) < 0.02
    assert float(angle.max()) < 1.0
    lo, hi = torch.tensor(ROOM_MIN) + 0.2, torch.tensor(ROOM_MAX) - 0.2
    assert ((P[:, :3, 3] > lo) & (P[:, :3, 3] < hi)).all()
    o0, o1 = ds.object_poses(0.0)["cube"], ds.object_poses(ds.timestamps[-1])["cube"]
    moved = float((o1[:3, 3] - o0[:3, 3]).norm())
    turned = math.degrees(math.acos((float((o0[:3, :3].T @ o1[:3, :3]).trace()) - 1) / 2))
    assert 0.5 < moved < 1.0 and 45 < turned < 90
    assert list(ds.object_poses(1.0)) == ds.object_names == ["cube"]
    still = MovingCubeSequence(num_frames=10, width=16, height=16, camera_speed=0.0, object_speed=0.0)
    assert torch.equal(still.camera_pose(0), still.camera_pose(9))
    assert torch.equal(still.object_poses(0.0)["cube"], still.object_poses(5.0)["cube"])


def test_determinism_and_noise_statistics():
    kw = dict(num_frames=3, width=160, height=120)
    a, b = MovingCubeSequence(seed=3, **kw), MovingCubeSequence(seed=3, **kw)
    other = MovingCubeSequence(seed=4, **kw)
    fa, fb, fo = a[2], b[2], other[2]
    assert torch.equal(fa.rgb, fb.rgb) and torch.equal(fa.depth, fb.depth) and torch.equal(fa.mask, fb.mask)
    assert not torch.equal(fa.depth, fo.depth) and torch.equal(fa.mask, fo.mask)
    clean = a.render(2, noise=False)
    assert torch.equal(clean.depth, other.render(2, noise=False).depth)
    assert torch.equal(clean.depth, MovingCubeSequence(depth_noise=False, **kw)[2].depth)
    valid = fa.depth > 0
    frac = float(valid.float().mean())
    assert 0.85 < frac < 0.995
    z = clean.depth.double()[valid]
    r = (fa.depth.double()[valid] - z) / _sigma(z)
    assert abs(float(r.mean())) < 0.05 and 0.9 < float(r.std()) < 1.1
    # Holes concentrate along silhouettes (depth discontinuities).
    zc = clean.depth
    edge = torch.zeros_like(valid)
    jump = (zc[:, 1:] - zc[:, :-1]).abs() > 0.1
    edge[:, 1:] |= jump
    edge[:, :-1] |= jump
    assert float((~valid)[edge].float().mean()) > 3 * float((~valid)[~edge].float().mean())
    noise = fa.rgb - clean.rgb
    assert 0.005 < float(noise.std()) < 0.02
    assert torch.equal((fa.rgb * 255).round() / 255, fa.rgb)  # 8-bit quantised


def test_cache_round_trip_and_corrupt_recovery(tmp_path, monkeypatch):
    kw = dict(num_frames=4, width=80, height=60, seed=1)
    ds = MovingCubeSequence(cache_dir=str(tmp_path), **kw)
    frame = ds[2]
    files = list(tmp_path.glob("synthetic_cube-*/frame_00002.npz"))
    assert len(files) == 1 and files[0].parent.name == f"synthetic_cube-{ds.render_key()}"
    assert not list(tmp_path.glob("synthetic_cube-*/.*.tmp"))
    uncached = MovingCubeSequence(**kw)[2]

    def no_render(*args, **kwargs):
        raise AssertionError("rendered although the frame is cached")

    again = MovingCubeSequence(cache_dir=str(tmp_path), **kw)
    monkeypatch.setattr(again, "render_arrays", no_render)
    cached = again[2]
    for f in (cached, uncached):
        assert torch.equal(f.rgb, frame.rgb) and torch.equal(f.depth, frame.depth)
        assert torch.equal(f.mask, frame.mask) and torch.equal(f.gt_pose, frame.gt_pose)
        assert f.timestamp == frame.timestamp and f.index == frame.index
    # Another configuration gets its own folder.
    assert MovingCubeSequence(cache_dir=str(tmp_path), **{**kw, "seed": 2}).render_key() != ds.render_key()
    # Corrupt or truncated file: re-rendered and rewritten.
    good = files[0].read_bytes()
    for bad in (b"not a zip file", good[: len(good) // 2], good[:-40]):
        files[0].write_bytes(bad)
        recovered = MovingCubeSequence(cache_dir=str(tmp_path), **kw)[2]
        assert torch.equal(recovered.depth, frame.depth) and torch.equal(recovered.rgb, frame.rgb)
        assert torch.equal(recovered.mask, frame.mask)
        with np.load(files[0]) as z:
            assert z["depth"].shape == (60, 80)
