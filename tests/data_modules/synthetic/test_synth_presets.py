"""Every preset renders, is physically consistent, is seeded, and has the property its name promises."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from data_modules.synthetic import PRESETS, SyntheticSequence
from data_modules.synthetic.shapes import Box, Cylinder, Sphere, bound_half, shape_raycast, shape_sdf

PROCEDURAL = [name for name in PRESETS if name != "cube"]
SMALL = dict(width=64, height=48, depth_noise=False, rgb_noise=0.0, cache_dir=None)


def _speeds(ds: SyntheticSequence, name: str) -> np.ndarray:
    """(N-1,) speed (m/s) of object ``name`` between consecutive frames."""
    c = np.stack([ds.object_poses(t)[name][:3, 3].numpy() for t in ds.timestamps])
    return np.linalg.norm(np.diff(c, axis=0), axis=1) * ds.fps


def _angles_deg(ds: SyntheticSequence) -> np.ndarray:
    """(N-1,) camera rotation (degrees) between consecutive frames."""
    P = ds.camera_poses().numpy()
    rel = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
    return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("name", list(PRESETS))
def test_every_preset_renders_and_is_physically_consistent(name):
    ds = SyntheticSequence(scene=name, num_frames=12, fps=2.4, **SMALL)  # 12 frames over ~5 s
    assert ds.name == f"synthetic_{name}" and ds.scene.description and PRESETS[name].summary
    seen = np.zeros(len(ds.object_names), dtype=bool)
    for i in range(len(ds)):
        t = float(ds.timestamps[i])
        labels = ds.labels(i)
        seen |= np.array([bool((labels == k + 1).any()) for k in range(len(ds.object_names))], dtype=bool)
        assert float(ds.sdf(ds.camera_pose(i)[:3, 3][None], t)) > 0.3  # the camera stays in free space
        placed = {p.obj.name: p for p in ds.placed(t)}
        for k, obj in enumerate(ds.object_names):  # no object cuts into furniture, walls or another object
            pts = ds.sample_surface(t, 300, name=obj, seed=i)
            assert float(ds.sdf(pts, t, part="static").min()) > -1e-9
            for other in ds.object_names[k + 1 :]:
                p = placed[other]
                assert float(shape_sdf(p.obj.shape, (pts - p.c) @ p.R).min()) > 0.02
    assert seen.all()  # every moving object shows up
    noisy = SyntheticSequence(scene=name, num_frames=2, width=64, height=48, cache_dir=None)[1]
    noisy.validate(name, ds.intrinsics)
    assert 0.6 < float((noisy.depth > 0).float().mean()) < 1.0  # holes (a larger share at 64 x 48)


def test_the_seed_selects_the_layout_and_scene_seed_decouples_it():
    for name in PROCEDURAL:
        a, b = (SyntheticSequence(scene=name, seed=s, num_frames=2, **SMALL) for s in (3, 4))
        assert repr(a.scene) == repr(SyntheticSequence(scene=name, seed=3, num_frames=2, **SMALL).scene)
        assert repr(a.scene) != repr(b.scene)
    assert repr(SyntheticSequence(seed=1, **SMALL).scene) == repr(SyntheticSequence(seed=2, **SMALL).scene)  # cube: fixed
    kw = dict(scene="crossing", num_frames=2, width=64, height=48, cache_dir=None)
    x, y = SyntheticSequence(seed=1, scene_seed=7, **kw), SyntheticSequence(seed=2, scene_seed=7, **kw)
    assert repr(x.scene) == repr(y.scene) and not torch.equal(x[1].depth, y[1].depth)
    assert torch.equal(x[1].depth, SyntheticSequence(seed=1, scene_seed=7, **kw)[1].depth)


def test_static_room_has_nothing_dynamic():
    ds = SyntheticSequence(scene="static_room", num_frames=8, fps=2.0, **SMALL)
    assert ds.object_names == [] and ds.object_poses(1.0) == {}
    assert not any(bool(ds[i].mask.any()) for i in range(len(ds)))
    assert ds.sample_surface(1.0, 100, part="dynamic").shape == (0, 3)
    assert bool(torch.isinf(ds.sdf(torch.zeros(4, 3), 1.0, part="dynamic")).all())
    with pytest.raises(KeyError):
        ds.dynamic_box(1.0)
    assert np.ptp(_angles_deg(ds).cumsum()) > 10  # the camera pans


def test_stop_and_go_rests_and_moves():
    ds = SyntheticSequence(scene="stop_and_go", num_frames=150, **SMALL)
    v = _speeds(ds, "pushed")
    rest = v == 0.0  # bit-identical consecutive poses
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, rest.astype(int), 0]) != 0))[::2]
    assert rest[:20].all() and runs.max() >= 20  # rests >= 2/3 s at a time (from the start)
    assert v.max() > 1.0 and (~rest).sum() > 20  # and really moves in between
    box = ds.dynamic_box(0.0)
    assert float(box[0][2] - box[1][2]) == pytest.approx(0.0, abs=1e-12)  # resting on the floor


def test_crossing_objects_cross_in_view():
    ds = SyntheticSequence(scene="crossing", num_frames=150, **SMALL)
    K = ds.intrinsics
    u, visible = {}, {}
    for name in ("far", "near"):
        c = torch.stack([ds.object_poses(t)[name][:3, 3] for t in ds.timestamps])
        cam = torch.einsum("nji,nj->ni", ds.camera_poses()[:, :3, :3], c - ds.camera_poses()[:, :3, 3])
        u[name] = (K.fx * cam[:, 0] / cam[:, 2] + K.cx).numpy()
        visible[name] = (cam[:, 2] > 0).numpy() & (u[name] > 0) & (u[name] < K.width)
    both = visible["far"] & visible["near"]
    order = np.sign(u["far"] - u["near"])[both]
    assert (order > 0).any() and (order < 0).any()  # their image order swaps while both are in view
    i = int(np.flatnonzero(both)[np.argmin(np.abs(u["far"] - u["near"])[both])])
    # At the crossing the near object hides part of the far one: some rays that end on "near" pass through "far".
    t, c2w = float(ds.timestamps[i]), ds.camera_pose(i)
    near_px = ds.labels(i) == 1 + ds.object_names.index("near")
    far = {p.obj.name: p for p in ds.placed(t)}["far"]
    rays = ds._rays[:, near_px]  # (3, n) camera-frame directions of the "near" pixels
    tk, _, _ = shape_raycast(far.obj.shape, (c2w[:3, 3] - far.c) @ far.R, far.R.T @ (c2w[:3, :3] @ rays))
    assert bool(torch.isfinite(tk).any())


def test_big_fast_is_big_and_fast():
    ds = SyntheticSequence(scene="big_fast", num_frames=150, **SMALL)
    assert 2 * float(ds.dynamic_box(0.0)[1].max()) >= 0.6
    assert _speeds(ds, "big_box").max() > 2.0
    assert max(float(ds[i].mask.float().mean()) for i in range(0, 150, 10)) > 0.08


def test_orbit_camera_circles_while_the_ball_circles_the_other_way():
    ds = SyntheticSequence(scene="orbit_ball", num_frames=150, **SMALL)
    cam = ds.camera_poses()[:, :3, 3].numpy()
    ball = np.stack([ds.object_poses(t)["ball"][:3, 3].numpy() for t in ds.timestamps])
    r = np.linalg.norm(cam[:, :2], axis=1)
    assert np.ptp(r) < 0.02 and np.ptp(np.linalg.norm(ball[:, :2], axis=1)) < 1e-9
    turn_cam = np.unwrap(np.arctan2(cam[:, 1], cam[:, 0]))
    turn_ball = np.unwrap(np.arctan2(ball[:, 1], ball[:, 0]))
    assert math.degrees(turn_cam[-1] - turn_cam[0]) > 60 and math.degrees(turn_ball[-1] - turn_ball[0]) < -200


def test_fast_turn_turns_fast_with_blur_and_exposure():
    ds = SyntheticSequence(scene="fast_turn", num_frames=150, width=64, height=48, cache_dir=None)
    assert ds.sensor.motion_blur == 5 and ds.sensor.exposure > 0
    speed = _angles_deg(ds) * ds.fps
    assert speed.max() > 150 and (speed < 5).sum() > 30  # whips between holds
    i = int(np.argmax(speed))
    kw = dict(scene="fast_turn", num_frames=150, width=128, height=96, cache_dir=None, rgb_noise=0.0)
    sharp = SyntheticSequence(sensor={"motion_blur": 0, "exposure": 0.0}, **kw)[i]
    warped = SyntheticSequence(sensor={"exposure": 0.0}, **kw)[i]
    exact = SyntheticSequence(sensor={"exposure": 0.0, "blur_exact": True}, **kw)[i]
    assert torch.equal(sharp.depth, warped.depth) and torch.equal(sharp.mask, exact.mask)  # blur touches colour only
    blur = float((sharp.rgb - exact.rgb).abs().mean())
    assert blur > 0.02 and float((warped.rgb - exact.rgb).abs().mean()) < 0.4 * blur  # the fast warp ~ exact renders


def test_three_objects_differ_in_shape_and_speed():
    ds = SyntheticSequence(scene="three_objects", num_frames=150, **SMALL)
    assert len(ds.object_names) == 3
    shapes = {type(m.shape) for m in ds.scene.movers}
    assert len(shapes) >= 2 and shapes <= {Box, Cylinder, Sphere}
    peaks = [_speeds(ds, n).max() for n in ds.object_names]
    assert len({round(p, 2) for p in peaks}) == 3 and min(peaks) < 0.5 < max(peaks)  # one turns in place
    assert ds.sensor.lateral > 0 and ds.sensor.quantization == 0.001
    sizes = [float(np.max(bound_half(m.shape))) for m in ds.scene.movers]
    assert max(sizes) / min(sizes) > 1.2


def test_door_is_thin_and_swings_on_its_hinge():
    ds = SyntheticSequence(scene="door", num_frames=90, **SMALL)
    door = ds.scene.movers[0]
    half = bound_half(door.shape)
    assert isinstance(door.shape, Box) and 2 * half.min() <= 0.04 and 2 * half[0] >= 0.6
    # The door's hinge-side edge (local x = -half_x) stays on one vertical line while the free edge sweeps.
    edge = np.array([-half[0], 0.0, 0.0, 1.0])
    free = np.array([half[0], 0.0, 0.0, 1.0])
    hinge_pts = np.stack([(ds.object_poses(t)["door"].numpy() @ edge)[:3] for t in ds.timestamps])
    free_pts = np.stack([(ds.object_poses(t)["door"].numpy() @ free)[:3] for t in ds.timestamps])
    assert np.ptp(hinge_pts, axis=0).max() < 0.025  # within the 1 cm gap's circle
    yaw = np.unwrap([math.atan2(*ds.object_poses(t)["door"].numpy()[1::-1, 0]) for t in ds.timestamps])
    assert math.degrees(np.ptp(yaw)) > 60 and np.ptp(free_pts[:, :2], axis=0).max() > 0.5


def test_breathing_ball_changes_radius_with_an_exact_sdf_and_visibility():
    ds = SyntheticSequence(scene="breathing", num_frames=90, **SMALL)
    radii = []
    for t in (0.0, 0.6, 1.2):
        c = ds.object_poses(t)["blob"][:3, 3]
        pts = ds.sample_surface(t, 200, name="blob", seed=1)
        r = (pts - c).norm(dim=-1)
        assert float(np.ptp(r.numpy())) < 1e-9  # a sphere at each time
        assert float(ds.sdf(pts, t, part="dynamic").abs().max()) < 1e-9
        radii.append(float(r[0]))
    assert max(radii) / min(radii) > 1.15  # non-rigid: the radius breathes
    # A point seen at t is carried to each frame's time with the scale, so what a frame sees stays seen.
    seen = ds.visible(ds.sample_surface(0.6, 400, name="blob", seed=2), 0.6, window=0.3, name="blob")
    assert 0.2 < float(seen.float().mean()) < 0.8
