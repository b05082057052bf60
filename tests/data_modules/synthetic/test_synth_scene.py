"""Scene geometry: ray casting agrees with the exact SDF, culling is exact, surface sampling and parts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_modules.synthetic.motion import Fixed, LookAtCamera, Orbit, SineCurve, look_at, pose_matrix
from data_modules.synthetic.render import pixel_rays, screen_rects
from data_modules.synthetic.scene import Room, Scene, SceneObject, place, raycast, sample_surface, scene_sdf
from data_modules.synthetic.shapes import CURVED, Box, Cylinder, Sphere
from data_modules.synthetic.textures import Texture

TEX = Texture(1, (0.5,) * 3, (0.3,) * 3, (1.0,) * 3, (0.0,) * 3)
ROOM = Room((-2.0, -2.0, 0.0), (2.0, 2.0, 2.5), (TEX,) * 6)
SCENE = Scene(
    ROOM,
    (SceneObject("table", Box((0.4, 0.3, 0.35)), TEX, Fixed((0.8, 0.9, 0.35), 0.3)),
     SceneObject("post", Cylinder(0.15, 0.5), TEX, Fixed((-0.9, 1.0, 0.5)))),
    (SceneObject("ball", Sphere(0.2), TEX, Orbit((0.0, 0.4, 0.6), 0.5, 1.0)),),
    LookAtCamera(SineCurve((0.0, -1.5, 1.3)), SineCurve((0.0, 0.6, 0.5))),
)
FX, W, H = 48.0, 64, 48
K = (FX, FX, (W - 1) / 2, (H - 1) / 2)


def _view(t: float) -> tuple[torch.Tensor, torch.Tensor, list]:
    c2w = torch.from_numpy(SCENE.camera.pose(t))
    dirs = (c2w[:3, :3] @ pixel_rays(*K, W, H).reshape(3, -1)).view(3, H, W)
    return c2w, dirs, place(SCENE, t)


@pytest.mark.parametrize("t", [0.0, 1.1, 2.9])
def test_raycast_lies_on_the_sdf_and_culling_is_exact(t):
    c2w, dirs, placed = _view(t)
    full = raycast(ROOM, placed, c2w[:3, 3], dirs)
    culled = raycast(ROOM, placed, c2w[:3, 3], dirs, screen_rects(placed, c2w, K, W, H))
    for a, b in ((full.depth, culled.depth), (full.prim, culled.prim), (full.face, culled.face), (full.local, culled.local)):
        assert torch.equal(a, b)
    o, d = c2w[:3, 3], dirs.reshape(3, -1).T
    z = full.depth.reshape(-1)
    assert bool(torch.isfinite(z).all())
    assert float(scene_sdf(ROOM, placed, o + z[:, None] * d).abs().max()) < 1e-9
    for frac in (0.5, 0.99):
        assert bool((scene_sdf(ROOM, placed, o + frac * z[:, None] * d) > 0).all())
    assert set(full.prim.unique().tolist()) == {0, 1, 2, 3}  # room, table, post, ball all in view
    # Hit points in the primitive's frame: the ball's are on its sphere, its faces curved.
    ball = full.prim == 3
    assert torch.allclose(full.local[:, ball].norm(dim=0), torch.full((int(ball.sum()),), 0.2, dtype=torch.float64))
    assert bool((full.face[ball] == CURVED).all()) and bool((full.cos > 0).all() and (full.cos <= 1 + 1e-12).all())


def test_sdf_parts_and_signs():
    placed = place(SCENE, 0.0)
    ball = placed[2].c
    p = torch.stack([ball, torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), torch.tensor([0.0, -1.0, 1.0], dtype=torch.float64)])
    assert torch.allclose(scene_sdf(ROOM, placed, p, "dynamic")[:1], torch.tensor([-0.2], dtype=torch.float64))
    assert float(scene_sdf(ROOM, placed, p)[1]) == pytest.approx(-0.5)  # above the ceiling
    assert float(scene_sdf(ROOM, placed, p, "static")[0]) > 0
    assert float(scene_sdf(ROOM, placed, p)[2]) == pytest.approx(1.0)  # 1 m above the floor, nearest surface
    with pytest.raises(ValueError):
        scene_sdf(ROOM, placed, p, "moving")


def test_sample_surface_selection_and_contact():
    placed = place(SCENE, 0.7)
    gen = torch.Generator().manual_seed(0)
    table = sample_surface(ROOM, placed, 4000, gen, names=("table",))
    local = (table - placed[0].c) @ placed[0].R
    assert float(scene_sdf(ROOM, placed, table).abs().max()) < 1e-9
    assert bool((local.abs() <= torch.tensor([0.4, 0.3, 0.35], dtype=torch.float64) + 1e-9).all())
    assert bool((local[:, 2] > -0.35 + 1e-9).all())  # the bottom touches the floor: never sampled
    static = sample_surface(ROOM, placed, 20_000, gen, part="static")
    floor = static[static[:, 2].abs() < 1e-12]
    under = ((floor[:, :2] - placed[0].c[:2]) @ placed[0].R[:2, :2]).abs()
    assert len(floor) > 1000 and not bool(((under[:, 0] < 0.39) & (under[:, 1] < 0.29)).any())
    dyn = sample_surface(ROOM, placed, 500, gen, part="dynamic")
    assert torch.allclose((dyn - placed[2].c).norm(dim=-1), torch.full((500,), 0.2, dtype=torch.float64))
    empty = Scene(ROOM, SCENE.statics, (), SCENE.camera)
    assert sample_surface(ROOM, place(empty, 0.0), 10, gen, part="dynamic").shape == (0, 3)


def test_culling_skips_primitives_behind_the_camera():
    at, towards = np.array([0.0, 0.3, 1.0]), np.array([0.0, -1.0, 1.0])
    rects = screen_rects(place(SCENE, 0.0), torch.from_numpy(pose_matrix(look_at(at, towards), at)), K, W, H)
    assert rects[0] is None and rects[1] is None  # table and post are behind the camera (y > 0.3)
