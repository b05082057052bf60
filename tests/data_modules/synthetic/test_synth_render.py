"""Rendering: colour is a property of the surface point, the same from any viewpoint; views are exact."""

from __future__ import annotations

import torch

from data_modules.synthetic import SyntheticSequence
from data_modules.synthetic.render import render_view


def test_a_surface_point_has_one_colour_from_every_view():
    ds = SyntheticSequence(scene="static_room", num_frames=60, width=64, height=48, depth_noise=False, rgb_noise=0.0)
    K = ds.intrinsics.K(dtype=torch.float64)
    a = ds.render(0, noise=False)
    # Points of frame 0 projected into frame 40 (another viewpoint), compared where 40 sees the same point.
    v, u = torch.meshgrid(torch.arange(ds.height, dtype=torch.float64), torch.arange(ds.width, dtype=torch.float64), indexing="ij")
    cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1) * a.depth.double()[..., None]
    world = cam.reshape(-1, 3) @ a.gt_pose[:3, :3].T + a.gt_pose[:3, 3]
    c2w = ds.camera_pose(40)
    cam_b = (world - c2w[:3, 3]) @ c2w[:3, :3]
    hit = ds.raycast(c2w, float(ds.timestamps[40]), cam_b / cam_b[:, 2:3])
    same = (hit.depth.reshape(-1) - cam_b[:, 2]).abs() < 1e-6
    assert int(same.sum()) > 500
    seen = ds.raycast(c2w, float(ds.timestamps[40]), cam_b[same] / cam_b[same, 2:3])  # exact rays, not pixel centres
    rgb_b = (ds._bank.colour(seen.prim.reshape(-1), seen.face.reshape(-1), seen.local.reshape(3, -1)) * 255).round()
    rgb_a = (a.rgb.reshape(-1, 3)[same] * 255).round()
    assert float((rgb_a - rgb_b).abs().max()) <= 1.0  # 8-bit rounding of the same colour


def test_views_and_labels_are_consistent():
    """render_view (culled, shaded) agrees with the plain ray cast of every pixel."""
    ds = SyntheticSequence(scene="crossing", num_frames=3, width=48, height=36, depth_noise=False, rgb_noise=0.0)
    rgb, depth, labels = ds.render_arrays(1, noise=False)
    t, K = float(ds.timestamps[1]), ds.intrinsics
    view = render_view(ds.scene.room, ds.placed(t), ds._bank, ds.camera_pose(1), ds._rays, (K.fx, K.fy, K.cx, K.cy))
    hit = ds.raycast(ds.camera_pose(1), t)
    assert torch.equal(view.depth, hit.depth) and torch.equal(view.prim, hit.prim) and torch.equal(view.cos, hit.cos)
    assert torch.equal(torch.from_numpy(depth), hit.depth.to(torch.float32))
    n_static = len(ds.scene.statics)
    assert torch.equal(torch.from_numpy(labels).long(), (hit.prim - n_static).clamp_min(0))
    assert rgb.dtype.name == "uint8" and rgb.shape == (36, 48, 3)
