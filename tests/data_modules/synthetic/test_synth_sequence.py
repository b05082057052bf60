"""SyntheticSequence ground truth: depth, masks, labels, poses, SDF, surfaces and visibility agree exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from data_modules.frame import DatasetError
from data_modules.synthetic import SyntheticSequence
from data_modules.synthetic.shapes import shape_sdf
from tivne.geometry import invert_pose, pixel_grid, pixel_to_ray, project, se3_exp, transform_points

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def busy() -> SyntheticSequence:
    """Three moving objects (boxes, cylinders, spheres), noise-free 80x60, 2 s at 5 fps."""
    return SyntheticSequence(scene="three_objects", num_frames=10, fps=5.0, width=80, height=60, depth_noise=False,
                             rgb_noise=0.0, cache_dir=None)


def _points(ds: SyntheticSequence, i: int, depth: torch.Tensor) -> torch.Tensor:
    """(H*W, 3) world points of frame i's depth (GT pose, pinhole back-projection)."""
    K = ds.intrinsics.K(dtype=torch.float64)
    cam = pixel_to_ray(pixel_grid(ds.height, ds.width, dtype=torch.float64), K) * depth.double()[..., None]
    return transform_points(ds.camera_pose(i), cam.reshape(-1, 3))


@pytest.mark.parametrize("i", [0, 4, 9])
def test_depth_lies_on_the_scene_and_labels_name_the_surface(busy, i):
    f, t = busy[i], float(busy.timestamps[i])
    assert (f.depth > 0).all()
    p = _points(busy, i, f.depth)
    assert float(busy.sdf(p, t).abs().max()) < 1e-6  # < 1 um: float32 depth rounding only
    o = busy.camera_pose(i)[:3, 3]
    assert bool((busy.sdf(o + 0.98 * (p - o), t) > 0).all())  # the ray is free up to the surface
    labels = busy.labels(i).reshape(-1)
    assert torch.equal(labels > 0, f.mask.reshape(-1))
    assert torch.equal(f.instances.reshape(-1), labels)  # the frame carries the instance ids
    placed = {q.obj.name: q for q in busy.placed(t)}
    for k, name in enumerate(busy.object_names):  # each object's pixels lie on that object, all others don't
        q = placed[name]
        on_obj = shape_sdf(q.obj.shape, (p - q.c) @ q.R).abs() < 1e-6
        assert torch.equal(on_obj, labels == k + 1)
    assert float(busy.sdf(p[labels == 0], t, part="static").abs().max()) < 1e-6


def test_render_matches_cached_frames_and_noise_free_render(tmp_path):
    kw = dict(scene="crossing", num_frames=3, width=48, height=36, seed=2)
    ds = SyntheticSequence(cache_dir=tmp_path, **kw)
    a = ds[2]
    b = SyntheticSequence(cache_dir=tmp_path, **kw)[2]  # from the cache
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and torch.equal(a.mask, b.mask)
    assert list(tmp_path.glob("synthetic_crossing-*/frame_00002.npz"))
    clean = ds.render(2, noise=False)
    assert torch.equal(clean.mask, a.mask) and torch.equal(clean.gt_pose, a.gt_pose)
    valid = a.depth > 0
    assert 0.001 < float((a.depth - clean.depth)[valid].abs().mean()) < 0.02


def test_gt_poses_carry_static_points_between_frames():
    """Static points of frame 0, moved into frame 12 with GT poses, match its depth to < 1 mm."""
    ds = SyntheticSequence(scene="orbit_ball", num_frames=13, width=96, height=72, depth_noise=False, rgb_noise=0.0)
    a, b = ds[0], ds[12]
    K = ds.intrinsics.K(dtype=torch.float64)
    pa = (pixel_to_ray(pixel_grid(ds.height, ds.width, dtype=torch.float64), K) * a.depth.double()[..., None])[~a.mask]
    uv, z = project(transform_points(invert_pose(b.gt_pose) @ a.gt_pose, pa), K)
    u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
    ok = (u >= 0) & (v >= 0) & (u < ds.width) & (v < ds.height) & (z > 0)
    # Exact check through the scene: the point seen at a's pixel is on the static surface at b's time.
    world = transform_points(a.gt_pose, pa[ok])
    assert float(ds.sdf(world, float(ds.timestamps[12]), part="static").abs().max()) < 1e-6
    # ... and where b sees it unoccluded, b's ray-cast depth along that point's own ray is its depth.
    hit = ds.raycast(b.gt_pose, float(ds.timestamps[12]), (transform_points(invert_pose(b.gt_pose), world) / z[ok, None]))
    seen = (hit.depth.reshape(-1) - z[ok]).abs() < 1e-3
    assert seen.float().mean() > 0.5


def test_object_poses_carry_object_surfaces(busy):
    for name in busy.object_names:
        pts = busy.sample_surface(0.3, 500, name=name, seed=1)
        T0, T1 = busy.object_poses(0.3)[name], busy.object_poses(1.7)[name]
        moved = transform_points(T1 @ invert_pose(T0), pts)
        assert float(busy.sdf(moved, 1.7, part="dynamic").abs().max()) < 1e-9
        c, h, R = busy.dynamic_box(1.7, name)
        assert bool((((moved - c) @ R).abs() <= h + 1e-9).all())
    with pytest.raises(KeyError):
        busy.dynamic_box(0.0, "sofa")
    assert busy.dynamic_box(0.0)[0].shape == (3,)  # the first object by default


def test_visibility_of_a_hidden_face():
    """The cube preset: at t, faces turned away from the camera are never seen, faces turned to it are
    (where nothing is in between); a wider window sees at least as much."""
    ds = SyntheticSequence(scene="cube", num_frames=30, width=80, height=60, depth_noise=False, rgb_noise=0.0)
    t = float(ds.timestamps[15])
    pts = ds.sample_surface(t, 3000, name="cube", seed=0)
    c, _, R = ds.dynamic_box(t)
    local = (pts - c) @ R
    axis = local.abs().argmax(-1)
    normal = torch.zeros_like(local).scatter_(1, axis[:, None], torch.sign(local.gather(1, axis[:, None]))) @ R.T
    facing = ((ds.camera_pose(15)[:3, 3] - pts) * normal).sum(-1) > 0
    now = ds.visible(pts, t, window=0.0, name="cube")
    assert not bool(now[~facing].any())  # back faces hidden (by the cube itself)
    assert float(now[facing].float().mean()) > 0.9
    wide = ds.visible(pts, t, window=0.5, name="cube")
    assert bool((wide | ~now).all()) and int(wide.sum()) >= int(now.sum())
    floor = ds.sample_surface(t, 2000, part="static", seed=3)
    static_seen = ds.visible(floor, t, window=0.0)
    behind = (floor - ds.camera_pose(15)[:3, 3]) @ ds.camera_pose(15)[:3, 2] < 0
    assert not bool(static_seen[behind].any()) and bool(static_seen.any())
    with pytest.raises(KeyError):
        ds.visible(pts, t, name="box_a")  # a static object: its points do not move


def test_sensor_settings_come_from_preset_then_caller():
    assert SyntheticSequence(scene="fast_turn", num_frames=2, width=32, height=24).sensor.motion_blur == 5
    ds = SyntheticSequence(scene="fast_turn", num_frames=2, width=32, height=24, sensor={"motion_blur": 0, "holes": None})
    assert ds.sensor.motion_blur == 0 and ds.sensor.holes == 4.0  # None keeps the preset's value
    assert SyntheticSequence(num_frames=2, width=32, height=24, rgb_noise=0.05).sensor.rgb_noise == 0.05
    with pytest.raises(DatasetError, match="dataset.sensor.wobble: unknown sensor setting"):
        SyntheticSequence(num_frames=2, width=32, height=24, sensor={"wobble": 1})
    with pytest.raises(DatasetError, match="dataset.sensor.shutter"):
        SyntheticSequence(num_frames=2, width=32, height=24, sensor={"shutter": 2.0})
    a = SyntheticSequence(num_frames=2, width=32, height=24, sensor={"lateral": 0.5})
    assert a.render_key() != SyntheticSequence(num_frames=2, width=32, height=24).render_key()


@pytest.mark.parametrize("overrides, name, scene", [
    (["dataset=cube"], "cube", "cube"),
    (["dataset=synthetic"], "synthetic_cube", "cube"),
    (["dataset=synthetic", "dataset.scene=stop_and_go", "dataset.sensor.quantization=0.001"], "synthetic_stop_and_go", "stop_and_go"),
])
def test_hydra_configs(overrides, name, scene):
    small = ["dataset.width=32", "dataset.height=24", "dataset.num_frames=2", "dataset.cache_dir=null"]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides + small, return_hydra_config=True)
    assert cfg.hydra.run.dir.startswith(f"outputs/{name}/")
    ds = instantiate(cfg.dataset)
    assert isinstance(ds, SyntheticSequence) and ds.name == name and ds.scene_name == scene and len(ds) == 2
    if scene == "stop_and_go":
        assert ds.sensor.quantization == 0.001 and ds.sensor.lateral == 0.0
    if overrides == ["dataset=cube"]:
        assert ds.sensor.rgb_noise == 0.01 and ds.sensor.depth_noise and ds.seed == 0
    np.testing.assert_array_equal(ds.timestamps, [0.0, 1 / 30])


def test_render_at_a_frames_pose_and_time_is_that_frames_clean_render():
    ds = SyntheticSequence("crossing", num_frames=4, width=48, height=36, cache_dir=None)
    frame = ds.render(2, noise=False)
    rgb, depth, labels = ds.render_at(ds.camera_pose(2), float(ds.timestamps[2]))
    assert torch.equal(depth, frame.depth) and torch.equal(labels > 0, frame.mask)
    assert torch.allclose(rgb, frame.rgb, atol=1.5 / 255)


def test_a_rolling_shutter_render_sees_each_band_of_rows_from_where_the_camera_was_then():
    """Still, it is the global render; turning, its middle rows are the render at the frame's pose and
    its first rows the render from the pose readout_s / 2 earlier."""
    ds = SyntheticSequence("cube", num_frames=2, width=48, height=36, cache_dir=None)
    P, t = ds.camera_pose(0), 0.0
    rgb, depth, _ = ds.render_at(P, t)
    still = ds.render_rolling_shutter(P, torch.zeros(6), 0.03, t)
    assert torch.equal(still[0], rgb) and torch.equal(still[1], depth)
    velocity = torch.tensor([0.3, 0.0, 0.0, 0.0, 4.0, 0.0], dtype=torch.float64)  # 230 °/s about the camera's y
    moving_rgb, moving = ds.render_rolling_shutter(P, velocity, 0.03, t, band=1)
    middle = slice(17, 19)  # rows 17 and 18 are read 1/72 of the readout either side of the middle
    assert (moving[middle] - depth[middle]).abs().max() < 0.05
    first = ds.render_at(P @ se3_exp(-(35 / 2) / 36 * 0.03 * velocity), t)[1]
    assert torch.equal(moving[0], first[0]) and not torch.equal(moving[0], depth[0])
