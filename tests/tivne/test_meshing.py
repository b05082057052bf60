"""Mesh extraction on fields whose SDF is known, and the mesh CLI on a tiny saved checkpoint."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from tivne.config import FieldConfig, MeshConfig
from tivne.field.clock import Clock
from tivne.field.networks import FieldOutputs, TimeVaryingField
from tivne.field.objects import ObjectField, ObjectSlot
from tivne.field.voxels import unpack_keys
from tivne.mesh import mesh_run, select_mesh_times
from tivne.meshing import DepthViews, carve_free_space, cull_backfaces, extract_mesh, free_space_votes, mesh_at, save_mesh
from tivne.render.rays import View
from tivne.slam.checkpoint import save_checkpoint

RADIUS = 0.3
TRUNCATION = 0.05
COLOUR = (0.2, 0.4, 0.6)
REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import run_commands  # noqa: E402


def sphere_surface(n: int = 4000, radius: float = RADIUS) -> torch.Tensor:
    """(n, 3) points on a sphere at the origin."""
    g = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    return radius * g / g.norm(dim=-1, keepdim=True)


class AnalyticSphere(TimeVaryingField):
    """A field whose SDF is the exact sphere's (truncation units) inside allocated voxels."""

    def forward(self, points: torch.Tensor, tau: torch.Tensor) -> FieldOutputs:
        valid = self.grid.contains(points)
        d = (points.norm(dim=-1) - RADIUS) / TRUNCATION
        sdf = torch.where(valid, d, torch.ones_like(d))
        rgb = torch.where(valid[:, None], torch.tensor(COLOUR).expand(len(points), 3), torch.zeros(len(points), 3))
        return FieldOutputs(sdf, rgb, valid, torch.zeros_like(d))


def analytic_sphere(dilation: int = 1) -> AnalyticSphere:
    field = AnalyticSphere(time=False, voxel_size=0.1, capacity=64)
    field.grid.allocate(sphere_surface(), dilation=dilation)
    return field


def field_kwargs(time: bool) -> dict:
    return dict(time=time, voxel_size=0.1, embed_dim=4, capacity=64, hidden_dim=8, num_hidden=3, time_frequencies=1, surface_cell=0.0)


def embedded_sphere(time: bool, field: TimeVaryingField | None = None) -> TimeVaryingField:
    """A real TimeVaryingField (``field``, default a new one) set by hand so that SDF = trilinear
    interpolation of the sphere's SDF.

    Embedding column 0 holds the corner SDF; the canonical MLP passes it through as relu(e0) - relu(-e0)
    and the colour head outputs the constant COLOUR. Θd stays zero-initialised (Δe = 0).
    """
    field = TimeVaryingField(**field_kwargs(time)) if field is None else field
    grid = field.grid
    grid.allocate(sphere_surface(), dilation=1)
    with torch.no_grad():
        corners = unpack_keys(grid.corner_keys).float() * grid.voxel_size
        grid.embeddings.zero_()
        grid.embeddings[grid.corner_rows, 0] = (corners.norm(dim=-1) - RADIUS) / TRUNCATION
        linears = [m for m in field.canonical.trunk if isinstance(m, torch.nn.Linear)]
        for layer in linears:
            layer.weight.zero_()
            layer.bias.zero_()
        linears[0].weight[0, 0], linears[0].weight[1, 0] = 1.0, -1.0
        for layer in linears[1:]:
            layer.weight[0, 0] = layer.weight[1, 1] = 1.0
        head = field.canonical.sdf_head
        head.weight.zero_()
        head.bias.zero_()
        head.weight[0, 0], head.weight[0, 1] = 1.0, -1.0
        field.canonical.color_head.weight.zero_()
        field.canonical.color_head.bias.copy_(torch.logit(torch.tensor(COLOUR)))
    return field.eval()


def radial_error(mesh: trimesh.Trimesh) -> np.ndarray:
    return np.abs(np.linalg.norm(mesh.vertices, axis=1) - RADIUS)


def test_sphere_vertices_on_surface_watertight_outward_coloured():
    res = 0.03
    mesh = extract_mesh(analytic_sphere(), tau=0.0, resolution=res)
    assert len(mesh.faces) > 500
    assert radial_error(mesh).max() < res / 2
    assert mesh.is_watertight
    assert mesh.volume > 0  # faces towards free space (positive SDF)
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * RADIUS**3, rel=0.03)
    colours = np.asarray(mesh.visual.vertex_colors)
    assert colours.dtype == np.uint8 and colours.shape == (len(mesh.vertices), 4)
    assert (colours == np.round(np.array([*COLOUR, 1.0]) * 255).astype(np.uint8)).all()


@pytest.mark.parametrize("brick, slab_points", [(3, 1 << 21), (16, 300), (64, 1 << 21)])
def test_bricks_give_the_same_welded_mesh(brick, slab_points):
    field = analytic_sphere()
    whole = extract_mesh(field, 0.0, resolution=0.03, brick=16)
    parts = extract_mesh(field, 0.0, resolution=0.03, brick=brick, slab_points=slab_points)  # 300: one brick per batch
    assert parts.is_watertight  # seams between bricks welded
    assert len(parts.vertices) == len(whole.vertices) and len(parts.faces) == len(whole.faces)
    assert np.allclose(np.sort(parts.vertices, axis=0), np.sort(whole.vertices, axis=0))


def test_no_surface_outside_allocated_voxels():
    # Only a thin band (no dilation) and only the upper half: the SDF is negative next to
    # unallocated space all over, which would give spurious walls without the cell mask.
    field = AnalyticSphere(time=False, voxel_size=0.1, capacity=64)
    pts = sphere_surface()
    field.grid.allocate(pts[pts[:, 2] > 0.1], dilation=0)
    res = 0.02
    mesh = extract_mesh(field, 0.0, resolution=res)
    assert len(mesh.faces) > 100
    assert radial_error(mesh).max() < res / 2
    z_min = float(field.grid.voxel_coords()[:, 2].min()) * field.grid.voxel_size
    assert mesh.vertices[:, 2].min() >= z_min - 1e-6
    inside = field.grid.contains(torch.as_tensor(mesh.vertices, dtype=torch.float32))
    assert inside.float().mean() > 0.99  # vertices exactly on a voxel face may hash to the empty side
    assert not mesh.is_watertight  # the open cut at the band's edges stays open


def test_empty_grid_and_no_crossing_give_empty_meshes(tmp_path):
    empty = extract_mesh(AnalyticSphere(time=False, voxel_size=0.1, capacity=8), 0.0, resolution=0.05)
    assert len(empty.vertices) == 0 and len(empty.faces) == 0
    far = AnalyticSphere(time=False, voxel_size=0.1, capacity=64)
    far.grid.allocate(torch.tensor([[2.0, 2.0, 2.0]]), dilation=1)  # all positive there
    assert len(extract_mesh(far, 0.0, resolution=0.05).faces) == 0
    path = save_mesh(empty, tmp_path / "empty.ply")
    assert len(trimesh.load(path, force="mesh", process=False).faces) == 0


@pytest.mark.parametrize("time", [True, False])
def test_real_field_with_known_embeddings(time):
    field = embedded_sphere(time)
    res = 0.03
    a = extract_mesh(field, tau=0.0, resolution=res)
    b = extract_mesh(field, tau=0.7, resolution=res)  # Θd is zero, so τ changes nothing here
    assert a.is_watertight and radial_error(a).max() < 0.02  # trilinear interpolation of the SDF
    assert np.allclose(a.vertices, b.vertices)
    assert (np.asarray(a.visual.vertex_colors)[:, :3] == np.round(np.array(COLOUR) * 255)).all()


def test_save_mesh_is_atomic_and_round_trips(tmp_path):
    mesh = extract_mesh(analytic_sphere(), 0.0, resolution=0.05)
    path = save_mesh(mesh, tmp_path / "sub" / "m.ply")
    back = trimesh.load(path, force="mesh", process=False)
    assert len(back.faces) == len(mesh.faces) and np.allclose(back.vertices, mesh.vertices, atol=1e-6)
    assert np.array_equal(np.asarray(back.visual.vertex_colors), np.asarray(mesh.visual.vertex_colors))
    assert [p.name for p in path.parent.iterdir()] == ["m.ply"]  # no temporary left behind


def test_select_mesh_times():
    stamps = [0.0, 0.1, 0.2, 0.3, 0.4]
    assert select_mesh_times(stamps) == [0.0, 0.4]
    assert select_mesh_times([0.5]) == [0.5]
    assert select_mesh_times(stamps, every=2) == [0.0, 0.2, 0.4]
    assert select_mesh_times(stamps, times=[0.15, 0.4005]) == [0.15, 0.4]  # clamped within 1 ms
    with pytest.raises(ValueError, match="outside the recorded range"):
        select_mesh_times(stamps, times=[0.5])
    with pytest.raises(ValueError, match="not both"):
        select_mesh_times(stamps, times=[0.1], every=2)
    with pytest.raises(ValueError, match="every"):
        select_mesh_times(stamps, every=0)


def outside_cameras(n: int) -> torch.Tensor:
    """(n, 4, 4) camera poses 1.5 m in front of the sphere (a camera inside it would see every face
    from behind, and back-face culling would rightly drop them all)."""
    poses = torch.eye(4).repeat(n, 1, 1)
    poses[:, 2, 3] = -1.5
    return poses


def saved_run(tmp_path: Path) -> Path:
    field = embedded_sphere(time=True)
    stamps = [10.0, 10.1, 10.2]
    save_checkpoint(tmp_path / "checkpoints" / "slam.pt", field, stamps, outside_cameras(3), Clock(10.0, field.time_scale))
    return tmp_path


def test_mesh_run_every(tmp_path):
    run_dir = saved_run(tmp_path)
    written = mesh_run(run_dir, MeshConfig(resolution=0.05), every=1, device="cpu")
    assert [round(t, 3) for t, *_ in written] == [10.0, 10.1, 10.2]
    assert sorted(p.name for p in (run_dir / "meshes").iterdir()) == ["mesh_t10.000.ply", "mesh_t10.100.ply", "mesh_t10.200.ply"]
    assert all(n_faces > 0 for _, _, n_faces, _ in written)


def test_cli_round_trip_and_errors(tmp_path):
    run_dir = saved_run(tmp_path)
    # The three command lines in one worker process (tests/cli_worker.py), the refusal whose stderr
    # must be exactly one line first: it starts with nothing imported, as a new process does.
    outside, out, missing = run_commands([
        ("tivne.mesh", [f"run_dir={run_dir}", "mesh.times=[11.0]"]),
        ("tivne.mesh", [f"run_dir={run_dir}", "mesh.times=[10.0,10.2]", "mesh.resolution=0.05"]),
        ("tivne.mesh", [f"run_dir={tmp_path / 'nope'}"]),
    ], cwd=REPO)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("t=10.000s vertices=") and "mesh_t10.200.ply" in lines[1]
    for name in ("mesh_t10.000.ply", "mesh_t10.200.ply"):
        mesh = trimesh.load(run_dir / "meshes" / name, force="mesh", process=False)
        assert len(mesh.faces) > 100 and radial_error(mesh).max() < 0.03
    assert not (run_dir / "outputs").exists() and not (REPO / "mesh.log").exists()

    assert outside.returncode == 2 and outside.stderr.startswith("error:") and "outside the recorded range" in outside.stderr
    assert len(outside.stderr.strip().splitlines()) == 1

    assert missing.returncode == 2 and missing.stderr.startswith("error:") and "Traceback" not in missing.stderr


class SphereWithGhost(AnalyticSphere):
    """The sphere plus a spurious negative blob in an allocated but never observed voxel, as the
    unsupervised dilation shell of a real map has them."""

    ghost = torch.zeros(3)

    def forward(self, points: torch.Tensor, tau: torch.Tensor) -> FieldOutputs:
        out = super().forward(points, tau)
        blob = ((points - self.ghost).norm(dim=-1) - 0.03) / TRUNCATION
        out.sdf = torch.where(out.valid, torch.minimum(out.sdf, blob), out.sdf)
        return out


def test_min_hits_keeps_the_mesh_to_observed_voxels():
    field = SphereWithGhost(time=False, voxel_size=0.1, capacity=64)
    field.grid.allocate(sphere_surface(), dilation=1)
    coords, hits = field.grid.voxel_coords(), field.grid.voxel_hits
    centres = (coords.float() + 0.5) * field.grid.voxel_size
    # a shell voxel whose 26 neighbours are allocated too, far from the sphere surface
    far = (centres.norm(dim=-1) - RADIUS).abs() > 0.15
    field.ghost = centres[torch.nonzero((hits == 0) & far)[0, 0]]
    with_ghost = extract_mesh(field, 0.0, resolution=0.02)
    observed = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1))
    near_ghost = lambda mesh: int(((torch.as_tensor(mesh.vertices) - field.ghost.double()).norm(dim=-1) < 0.05).sum())
    assert near_ghost(with_ghost) > 10 and near_ghost(observed) == 0
    assert radial_error(observed).max() < 0.01
    # the sphere itself survives: its area is within 5% of the full extraction's sphere part
    sphere_part = with_ghost.area - 4 * np.pi * 0.03**2
    assert abs(observed.area - sphere_part) / sphere_part < 0.05


class MovingBall(AnalyticSphere):
    """A ball of radius 0.15 that the field (wrongly) still holds at both places it was seen: at
    x = -0.5 when τ = 0 and at x = +0.5 when τ = 1 (a trail the field has not forgotten)."""

    def forward(self, points: torch.Tensor, tau: torch.Tensor) -> FieldOutputs:
        out = super().forward(points, tau)
        centres = torch.tensor([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
        d = ((points[:, None, :] - centres).norm(dim=-1).min(dim=1).values - 0.15) / TRUNCATION
        out.sdf = torch.where(out.valid, d, out.sdf)
        return out


def ball_surface(centre_x: float) -> torch.Tensor:
    return sphere_surface(radius=0.15) + torch.tensor([centre_x, 0.0, 0.0])


def test_dynamic_window_shows_a_moving_object_only_where_it_was_seen_then():
    field = MovingBall(time=True, voxel_size=0.1, capacity=64)
    for tau, x in ((0.0, -0.5), (1.0, 0.5)):
        pts = ball_surface(x)
        field.grid.allocate(pts, dilation=1, dynamic=torch.ones(len(pts), dtype=torch.bool), tau=tau)
    sides = lambda mesh: (int((mesh.vertices[:, 0] < 0).sum()), int((mesh.vertices[:, 0] > 0).sum()))
    at0 = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1, dynamic_window=0.2))
    at1 = extract_mesh(field, 1.0, resolution=0.02, culling=MeshConfig(min_hits=1, dynamic_window=0.2))
    assert sides(at0)[0] > 100 and sides(at0)[1] == 0
    assert sides(at1)[0] == 0 and sides(at1)[1] > 100
    assert at0.is_watertight and at1.is_watertight  # the whole ball, no cut
    unculled = extract_mesh(field, 0.0, resolution=0.02)
    assert min(sides(unculled)) > 100  # the trail is in the field itself
    never = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1, dynamic_window=None))
    assert len(never.faces) == 0


class RoomWithBackSurface(AnalyticSphere):
    """Free space inside a spherical 'room' wall at r = 0.5 (seen from the centre); behind the wall the
    SDF turns positive again at r = 0.6, as an unsupervised field does past the sampled band."""

    def forward(self, points: torch.Tensor, tau: torch.Tensor) -> FieldOutputs:
        out = super().forward(points, tau)
        r = points.norm(dim=-1)
        d = torch.where(r < 0.55, 0.5 - r, r - 0.6) / TRUNCATION
        out.sdf = torch.where(out.valid, d, out.sdf)
        return out


def test_backface_culling_drops_the_surface_behind_the_wall():
    field = RoomWithBackSurface(time=False, voxel_size=0.1, capacity=256)
    for radius in (0.5, 0.6):
        field.grid.allocate(sphere_surface(8000, radius), dilation=1)
    centres = np.array([[0.0, 0.0, 0.0], [0.1, -0.05, 0.0]])  # cameras inside the room
    both = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1, backfaces=False), camera_centres=centres)
    culled = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1), camera_centres=centres)
    r_both = np.linalg.norm(both.vertices, axis=1)
    r_culled = np.linalg.norm(culled.vertices, axis=1)
    assert (np.abs(r_both - 0.6) < 0.01).sum() > 100 and (np.abs(r_both - 0.5) < 0.01).sum() > 100
    assert (np.abs(r_culled - 0.6) < 0.02).sum() == 0  # the back surface is gone ...
    assert abs(culled.area - 4 * np.pi * 0.5**2) / (4 * np.pi * 0.5**2) < 0.05  # ... the wall is whole
    # without camera centres nothing is culled
    assert len(extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1)).faces) == len(both.faces)


def test_cull_backfaces_keeps_faces_any_camera_sees_from_their_free_side():
    quad = trimesh.Trimesh(
        vertices=[[0, 0, 1], [1, 0, 1], [0, 1, 1], [0, 0, 2], [0, 1, 2], [1, 0, 2]],
        faces=[[0, 2, 1], [3, 5, 4]],  # normal -z (towards a camera at z < 1), normal +z
        process=False,
    )
    assert np.allclose(quad.face_normals, [[0, 0, -1], [0, 0, 1]])
    assert len(cull_backfaces(quad, np.array([[0.2, 0.2, 0.0]])).faces) == 1
    assert len(cull_backfaces(quad, np.array([[0.2, 0.2, 0.0], [0.2, 0.2, 3.0]])).faces) == 2
    assert len(cull_backfaces(quad, np.zeros((0, 3))).faces) == 2


class RoomWithMadeUpSurface(AnalyticSphere):
    """A spherical room wall at r = 0.5 seen from inside; behind it the SDF turns positive at r = 0.56
    and negative again at r = 0.62, a made-up surface that faces the cameras (as an unsupervised field
    can, past the sampled band), so back-face culling keeps it."""

    def forward(self, points: torch.Tensor, tau: torch.Tensor) -> FieldOutputs:
        out = super().forward(points, tau)
        r = points.norm(dim=-1)
        d = torch.where(r < 0.53, 0.5 - r, torch.where(r < 0.59, r - 0.56, 0.62 - r)) / TRUNCATION
        out.sdf = torch.where(out.valid, d, out.sdf)
        return out


def test_near_surface_drops_a_made_up_surface_that_faces_the_cameras():
    field = RoomWithMadeUpSurface(time=False, voxel_size=0.1, capacity=256, surface_cell=0.02)
    field.grid.allocate(sphere_surface(20000, 0.5), dilation=1)  # depth was seen on the wall only
    centres = np.array([[0.0, 0.0, 0.0], [0.1, -0.05, 0.0]])
    kept = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1, near_surface=False), camera_centres=centres)
    culled = extract_mesh(field, 0.0, resolution=0.02, culling=MeshConfig(min_hits=1), camera_centres=centres)
    r_kept, r_culled = np.linalg.norm(kept.vertices, axis=1), np.linalg.norm(culled.vertices, axis=1)
    assert (np.abs(r_kept - 0.62) < 0.01).sum() > 100  # back-face culling alone keeps it
    assert (np.abs(r_culled - 0.62) < 0.02).sum() == 0
    assert abs(culled.area - 4 * np.pi * 0.5**2) / (4 * np.pi * 0.5**2) < 0.05  # the wall is whole


def test_near_surface_keeps_a_moving_object_seen_around_the_mesh_time():
    field = MovingBall(time=True, voxel_size=0.1, capacity=64, surface_cell=0.02)
    pts = ball_surface(0.5)
    field.grid.allocate(pts, dilation=1, dynamic=torch.ones(len(pts), dtype=torch.bool), tau=1.0)
    assert field.grid.surface_keys.numel() == 0  # moving depth is not static surface
    field.grid.allocate(torch.tensor([[3.0, 0.0, 0.0]]))  # some static surface far away
    assert not field.grid.near_surface(pts).any()
    at1 = extract_mesh(field, 1.0, resolution=0.02, culling=MeshConfig(min_hits=1, dynamic_window=0.2))
    assert at1.is_watertight and len(at1.faces) > 100  # kept: on the moving object seen then


class MovingTrack:
    """Object-to-world poses (x = τ, z = 1, yaw = τ), observed for τ in [0, 2]."""

    box = torch.tensor([[-RADIUS] * 3, [RADIUS] * 3], dtype=torch.float64)

    def pose_at(self, tau: float) -> torch.Tensor:
        c, s = np.cos(tau), np.sin(tau)
        return torch.tensor([[c, -s, 0, tau], [s, c, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]], dtype=torch.float64)

    def observed_near(self, tau: float, window: float) -> bool:
        return -window <= tau <= 2 + window


def test_a_mesh_at_t_places_the_object_at_its_pose_and_meshes_it_once():
    field = ObjectField(FieldConfig(), window=0.1, mesh_resolution=0.02, time=False, voxel_size=0.1, capacity=64)
    field.set_tracks({1: MovingTrack()})
    field.slots[1] = ObjectSlot(analytic_sphere(), tau0=0.0)
    cfg = MeshConfig(resolution=0.02, min_hits=0, near_surface=False, backfaces=False)
    cache: dict = {}
    for tau in (0.5, 1.5):
        mesh = mesh_at(field, tau, cfg, cache=cache)
        centre = np.array([tau, 0.0, 1.0])
        r = np.linalg.norm(np.asarray(mesh.vertices) - centre, axis=1)
        assert len(mesh.faces) > 500 and np.abs(r - RADIUS).max() < 0.01
    assert sorted(k for k in cache if k[0] != "static") == [(1, None)]  # a rigid object is meshed once
    assert len(mesh_at(field, 3.0, cfg, cache=cache).faces) == 0  # not observed around τ = 3: not placed


FOCAL = 20.0
CAMERA_K = torch.tensor([[FOCAL, 0.0, 32.0], [0.0, FOCAL, 24.0], [0.0, 0.0, 1.0]])


def sphere_depth(centre: tuple[float, float, float], radius: float = RADIUS, far: float = 5.0) -> torch.Tensor:
    """(48, 64) z-depth of a sphere in front of a wall at ``far``, camera at the origin looking down +z (CAMERA_K)."""
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    d = torch.stack([(u - 32.0) / FOCAL, (v - 24.0) / FOCAL, torch.ones_like(u)], -1).double()
    c = torch.tensor(centre, dtype=torch.float64)
    b, cc = (d @ c) / (d * d).sum(-1), (c @ c - radius**2) / (d * d).sum(-1)
    disc = b * b - cc
    hit = torch.where(disc >= 0, b - disc.clamp_min(0).sqrt(), torch.full_like(b, far))
    return hit.clamp(max=far).float()


def test_free_space_votes_see_past_what_lies_in_front_and_see_what_lies_on_the_surface():
    depth = torch.full((48, 64), 2.0)
    points = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 2.01], [0.0, 0.0, 3.0], [10.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    past, seen = free_space_votes(points, depth, torch.eye(4), CAMERA_K)
    assert past.tolist() == [True, False, False, False, False]
    assert seen.tolist() == [False, True, False, False, False]
    depth[:, :] = 0.0  # no measurement: no vote either way
    past, seen = free_space_votes(points, depth, torch.eye(4), CAMERA_K)
    assert not past.any() and not seen.any()


def test_a_silhouette_never_sees_past_the_surface_it_bounds():
    depth = torch.full((48, 64), 3.0)
    depth[:, :32] = 1.0  # a foreground surface over the left half
    at_edge = torch.tensor([[(32.0 - 32.0) / FOCAL, 0.0, 1.0]])  # column 32: the first background pixel, beside the edge
    further = torch.tensor([[(37.0 - 32.0) / FOCAL, 0.0, 1.0]])
    assert not free_space_votes(at_edge, depth, torch.eye(4), CAMERA_K)[0].any()
    assert free_space_votes(further, depth, torch.eye(4), CAMERA_K)[0].all()


def test_carving_removes_a_floater_in_front_of_the_wall_and_keeps_the_wall():
    wall = trimesh.creation.box(extents=(0.6, 0.6, 0.02))
    wall.apply_translation((0.0, 0.0, 2.0))
    floater = trimesh.creation.box(extents=(0.2, 0.2, 0.02))
    floater.apply_translation((0.0, 0.0, 1.0))
    mesh = trimesh.util.concatenate([wall, floater])
    depth = torch.full((48, 64), 1.99)  # the wall's near face
    carved = carve_free_space(mesh, [(depth, torch.eye(4))], CAMERA_K)
    z = np.asarray(carved.triangles_center)[:, 2]
    assert (z > 1.5).sum() == len(wall.faces) and (z < 1.5).sum() == 0
    # a second frame that sees the floater as surface: one vote each way, kept
    seen = depth.clone()
    seen[20:29, 27:38] = 0.99
    assert len(carve_free_space(mesh, [(depth, torch.eye(4)), (seen, torch.eye(4))], CAMERA_K).faces) == len(mesh.faces)


def test_a_mesh_at_t_drops_the_static_surface_its_frames_see_through_and_leaves_the_objects():
    # the static field: a sphere at the origin; the cameras stand 1 m back on -z, looking down +z
    field = embedded_sphere(False, ObjectField(FieldConfig(), window=0.1, mesh_resolution=0.02, **field_kwargs(False)))
    cfg = MeshConfig(resolution=0.02, min_hits=0, near_surface=False, backfaces=False, carve_window=0.25)
    back = torch.eye(4)
    back[2, 3] = -1.0

    def views(depth: torch.Tensor, taus=(0.4, 0.6)) -> DepthViews:
        return DepthViews([View(i, t, torch.zeros(48, 64, 3), depth, None, back) for i, t in enumerate(taus)], CAMERA_K)

    whole = mesh_at(field, 0.5, cfg)
    assert len(whole.faces) > 500
    seen = mesh_at(field, 0.5, cfg, depth_views=views(sphere_depth((0.0, 0.0, 1.0))))
    assert len(seen.faces) == len(whole.faces)  # the frames see the sphere: every face stays
    through = mesh_at(field, 0.5, cfg, depth_views=views(torch.full((48, 64), 5.0)))
    assert len(through.faces) < 0.1 * len(whole.faces)  # they see the wall behind where it is: it was not there then
    # frames outside the window say nothing about τ = 0.5; carve_window=null turns carving off
    assert len(mesh_at(field, 0.5, cfg, depth_views=views(torch.full((48, 64), 5.0), taus=(1.5,))).faces) == len(whole.faces)
    off = MeshConfig(resolution=0.02, min_hits=0, near_surface=False, backfaces=False, carve_window=None)
    assert len(mesh_at(field, 0.5, off, depth_views=views(torch.full((48, 64), 5.0))).faces) == len(whole.faces)


def test_a_mesh_at_t_does_not_carve_the_objects():
    # a deforming object's mesh at τ differs from what the frames around τ saw at their own times
    field = ObjectField(FieldConfig(), window=0.1, mesh_resolution=0.02, time=False, voxel_size=0.1, capacity=64)
    field.set_tracks({1: MovingTrack()})
    field.slots[1] = ObjectSlot(analytic_sphere(), tau0=0.0)
    cfg = MeshConfig(resolution=0.02, min_hits=0, near_surface=False, backfaces=False, carve_window=0.25)
    empty = DepthViews([View(0, 0.5, torch.zeros(48, 64, 3), torch.full((48, 64), 5.0), None, torch.eye(4))], CAMERA_K)
    assert len(mesh_at(field, 0.5, cfg, depth_views=empty).faces) == len(mesh_at(field, 0.5, cfg).faces)
