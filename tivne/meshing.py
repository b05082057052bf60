"""Mesh extraction at any time τ: marching cubes restricted to the allocated voxels.

A lattice of step ``resolution`` spans the allocated voxels' bounding box, cut into bricks of
``brick`` cells per edge; only the bricks that touch an allocated voxel are visited (a room's
surface fills a few percent of its box). Batches of bricks are tested against the map at once
(:mod:`tivne.field.lattice`: integer hash keys, no float work per point), the field is evaluated
without gradients only at lattice points inside allocated (and, culling, observed) voxels, and
marching cubes runs per brick only on cells whose 8 corners are all inside, so no surface appears
where the map knows nothing. Neighbouring bricks share a plane of lattice points; the vertices on it
are welded, so the result is one mesh without seams.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage import measure

from data_modules.io import atomic_write
from data_modules.sensor import kinect_depth_sigma
from tivne.config import ConfigError, MeshConfig
from tivne.field.lattice import Lattice, brick_inside, bricks_for_voxels, lattice_for_voxels, observed_space
from tivne.field.networks import TimeVaryingField
from tivne.field.objects import ObjectField, static_only
from tivne.field.voxels import CORNER_OFFSETS
from tivne.geometry import depth_lookup, invert_pose, transform_points
from tivne.render.rays import View

# Lattice points per batch of bricks: ~60 bytes of temporaries each (keys, volume, masks), ~120 MB.
DEFAULT_SLAB_POINTS = 1 << 21
# Cells per brick edge: large enough that marching cubes' per-call cost is small against its work,
# small enough that bricks hug the surface (16 cells of 2 cm = 0.32 m, about 3 voxels).
DEFAULT_BRICK = 16
# Mesh times may lie this far outside the recorded range (seconds); they are clamped to it.
TIME_TOLERANCE_S = 1e-3
# Free-space carving: beyond the depth noise (3σ(z)), a face must lie this far in front of what a frame
# measured to count as seen past (two marching-cubes steps of 2 cm: the mesh's own quantisation).
CARVE_MARGIN_M = 0.04


def field_device(field: TimeVaryingField) -> torch.device:
    """The device the field's parameters and voxel hash live on."""
    return field.grid.voxel_keys.device


@torch.no_grad()
def query_field(
    field: TimeVaryingField, points: torch.Tensor, tau: float, chunk: int = 65536
) -> tuple[torch.Tensor, torch.Tensor]:
    """Field at world points at time τ, evaluated in chunks.

    Args:
        points: (P, 3) world points on the field's device.
        tau: normalised time (ignored by fields with ``time=False``).
        chunk: points per forward pass.
    Returns:
        sdf (P,) in truncation units (1 outside allocated voxels) and rgb (P, 3) in [0, 1].
    """
    sdf, rgb = [], []
    for start in range(0, points.shape[0], chunk):
        p = points[start : start + chunk]
        out = field(p, torch.full((p.shape[0],), float(tau), device=p.device, dtype=p.dtype))
        sdf.append(out.sdf)
        rgb.append(out.rgb)
    if not sdf:
        return points.new_zeros(0), points.new_zeros(0, 3)
    return torch.cat(sdf), torch.cat(rgb)


def cull_backfaces(mesh: trimesh.Trimesh, camera_centres: np.ndarray, chunk: int = 4096) -> trimesh.Trimesh:
    """Keep the faces whose normal (towards free space) points towards at least one camera.

    Args:
        mesh: faces oriented towards positive SDF (as :func:`extract_mesh` makes them).
        camera_centres: (N, 3) camera positions in the mesh's frame.
    Returns:
        the mesh without the faces every camera sees from behind (unreferenced vertices removed).
    """
    if len(mesh.faces) == 0 or len(camera_centres) == 0:
        return mesh
    centres = np.asarray(camera_centres, dtype=np.float64)
    normals, points = np.asarray(mesh.face_normals), np.asarray(mesh.triangles_center)
    seen = np.zeros(len(points), dtype=bool)
    for start in range(0, len(points), chunk):
        p, n = points[start : start + chunk], normals[start : start + chunk]
        # n . (c - p) > 0 for some camera c: the face's free side faces that camera (one GEMM per chunk)
        seen[start : start + chunk] = (n @ centres.T - (n * p).sum(1, keepdims=True)).max(1) > 0
    return keep_faces(mesh, seen)


def cull_unobserved_faces(
    mesh: trimesh.Trimesh, grid, tau: float, window: float | None, margin: float
) -> trimesh.Trimesh:
    """Keep the faces whose centre lies within one surface cell of observed static depth
    (``grid.near_surface``) or, when ``window`` is not None, within ``margin`` (per axis, as
    :func:`near_observed`) of a voxel where a moving object was seen around ``tau``.

    Args:
        mesh: in the grid's world frame; grid: a SparseVoxelGrid; tau: field time of the mesh.
    Returns:
        the mesh without the other faces (unreferenced vertices removed).
    """
    if len(mesh.faces) == 0:
        return mesh
    centres = torch.as_tensor(np.array(mesh.triangles_center, dtype=np.float32), device=grid.surface_keys.device)
    keep = grid.near_surface(centres)
    if window is not None:
        for offset in CORNER_OFFSETS.to(centres.device, centres.dtype):
            keep |= grid.dynamic_observed(centres + (2 * offset - 1) * margin, tau, window)
    return keep_faces(mesh, keep.cpu().numpy())


def keep_faces(mesh: trimesh.Trimesh, keep: np.ndarray) -> trimesh.Trimesh:
    """The mesh with only the faces flagged in ``keep`` (F,) bool, unreferenced vertices removed."""
    if keep.all():
        return mesh
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out if len(out.faces) else empty_mesh()


def near_observed(
    grid, points: torch.Tensor, min_hits: int, margin: float, tau: float | None = None, window: float = 0.0
) -> torch.Tensor:
    """Points within ``margin`` (per axis) of an observed voxel: one with >= ``min_hits`` static
    hits, or (``tau`` given) one where a moving object was seen within ``window`` of ``tau``
    (see ``SparseVoxelGrid.observed``).

    The margin keeps the marching-cubes cells that straddle the face between an observed voxel and
    its unobserved neighbour (a surface near that face crosses lattice edges reaching into it).

    Args:
        grid: a SparseVoxelGrid; points: (P, 3) world points.
    Returns:
        (P,) bool.
    """
    near = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    for offset in CORNER_OFFSETS.to(points.device, points.dtype):
        near |= grid.observed(points + (2 * offset - 1) * margin, min_hits, tau, window)
    return near


def weld_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge exactly coincident vertices and drop faces that collapse.

    Bricks share a lattice plane and interpolate its vertices from the same two lattice values, so
    seam vertices are exact duplicates; skimage's masked marching cubes also emits a few duplicates
    of its own (measured: 16 of 1896 on a sphere), which would break watertightness.

    Args:
        vertices: (N, 3) lattice-index coordinates.
        faces: (F, 3) int64.
    Returns:
        vertices (N', 3) and faces (F', 3) without duplicates or unreferenced vertices.
    """
    unique, inverse = np.unique(vertices, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[keep]
    used, compact = np.unique(faces, return_inverse=True)
    return unique[used], compact.reshape(-1, 3)


def empty_mesh() -> trimesh.Trimesh:
    """A mesh with no vertices and no faces (callers check ``len(mesh.faces) == 0`` and warn)."""
    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)


def brick_surfaces(
    field: TimeVaryingField, lattice: Lattice, bricks: torch.Tensor, brick: int, tau: float, culling: MeshConfig | None,
    chunk: int, batch_points: int,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Marching cubes brick by brick, the field evaluated in large batches of bricks.

    Args:
        bricks: (B, 3) int64 brick indices (:func:`bricks_for_voxels`); brick: cells per brick edge.
    Returns:
        per brick with a surface, vertices (V, 3) in lattice-index units and faces (F, 3) int64.
    """
    grid, device = field.grid, field_device(field)
    cull = culling is not None and (culling.min_hits > 0 or culling.dynamic_window is not None)
    window = None if culling is None else culling.dynamic_window
    space = observed_space(
        grid, lattice, lattice.step if cull else None, culling.min_hits if cull else 0,
        None if window is None else tau, window or 0.0,
    )
    axes = [lattice.axis(a, device) for a in range(3)]
    n = brick + 1  # a brick's points per axis; neighbours share a plane of points
    ar = torch.arange(n, device=device)
    per_batch = max(1, batch_points // n**3)
    verts, faces = [], []
    for start in range(0, len(bricks), per_batch):
        first = bricks[start : start + per_batch].to(device) * brick  # (nb, 3) first point index
        index = tuple(first[:, a, None] + ar for a in range(3))  # per axis (nb, n)
        inside = brick_inside(space, index, lattice.dims)  # (nb, n, n, n)
        if not inside.any():
            continue
        b, i, j, k = inside.nonzero(as_tuple=True)
        pts = torch.stack([axes[0][index[0][b, i]], axes[1][index[1][b, j]], axes[2][index[2][b, k]]], -1)
        volume = torch.ones(inside.shape, dtype=torch.float32, device=device)  # positive (free) where not evaluated
        volume[b, i, j, k] = query_field(field, pts, tau, chunk)[0].float()
        cells = inside[:, :-1, :-1, :-1].clone()
        for d in range(1, 8):
            dx, dy, dz = d >> 2, (d >> 1) & 1, d & 1
            cells &= inside[:, dx : n - 1 + dx, dy : n - 1 + dy, dz : n - 1 + dz]
        crossing = ((volume < 0) & inside).flatten(1).any(1) & ((volume > 0) & inside).flatten(1).any(1)
        live = torch.nonzero(cells.flatten(1).any(1) & crossing)[:, 0].cpu().numpy()
        cells_np, volume_np, first_np = cells.cpu().numpy(), volume.cpu().numpy(), first.cpu().numpy()
        for m in live:
            mask = np.zeros((n, n, n), dtype=bool)
            # skimage's Lewiner marching cubes tests ``mask`` at a cell's *max* corner (measured on
            # skimage 0.26; tests/tivne/test_meshing.py guards it)
            mask[1:, 1:, 1:] = cells_np[m]
            try:
                # 'descent' orients faces towards positive SDF (free space): a closed object gets a
                # positive trimesh volume (tested).
                v, f, _, _ = measure.marching_cubes(volume_np[m], level=0.0, mask=mask, gradient_direction="descent")
            except (RuntimeError, ValueError):  # no crossing inside the masked cells
                continue
            if len(f):
                verts.append(v.astype(np.float64) + first_np[m])
                faces.append(f.astype(np.int64))
    return verts, faces


def coloured_mesh(field: TimeVaryingField, verts: np.ndarray, faces: np.ndarray, tau: float, chunk: int) -> trimesh.Trimesh:
    """A mesh with RGBA uint8 vertex colours from the field at τ; zero-area faces dropped.

    Args:
        verts: (V, 3) world metres; faces: (F, 3).
    """
    pts = torch.from_numpy(verts).to(device=field_device(field), dtype=torch.float32)
    _, rgb = query_field(field, pts, tau, chunk)
    rgb8 = (rgb.clamp(0, 1).cpu().numpy() * 255.0).round().astype(np.uint8)
    colors = np.concatenate([rgb8, np.full((len(verts), 1), 255, np.uint8)], 1)
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False)
    area = mesh.area_faces
    if (area <= 0).any():  # an SDF value exactly 0 at a lattice point gives zero-area triangles
        mesh.update_faces(area > 0)
        mesh.remove_unreferenced_vertices()
    return mesh


@torch.no_grad()
def extract_mesh(
    field: TimeVaryingField,
    tau: float,
    resolution: float = 0.02,
    chunk: int = 65536,
    device: str | torch.device | None = None,
    slab_points: int = DEFAULT_SLAB_POINTS,
    culling: MeshConfig | None = None,
    camera_centres: np.ndarray | None = None,
    brick: int = DEFAULT_BRICK,
) -> trimesh.Trimesh:
    """Zero level set of the field at τ as one welded, vertex-coloured mesh in world metres.

    Args:
        field: the map; ``tau`` is ignored when ``field.time`` is False.
        tau: field time (see :func:`tivne.field.Clock`).
        resolution: lattice step in metres.
        chunk: points per field evaluation.
        device: where to evaluate; default the field's device (a field elsewhere is copied there).
        slab_points: lattice points per batch of bricks (bounds the temporaries).
        culling: keep the mesh to observed space (``min_hits``, ``dynamic_window``, ``near_surface``, ``backfaces`` of a
            :class:`tivne.config.MeshConfig`); None: every allocated voxel.
        camera_centres: (N, 3) camera positions of the run (for ``culling.backfaces``).
        brick: lattice cells per brick edge (marching cubes runs once per brick that holds a surface).
    Returns:
        ``trimesh.Trimesh`` with faces oriented towards free space (positive SDF) and RGBA uint8
        vertex colours from the field's rgb at τ; an empty mesh when no voxel is allocated or the
        field has no zero crossing inside the allocated voxels.
    """
    if resolution <= 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    if device is not None and torch.device(device) != field_device(field):
        field = copy.deepcopy(field).to(device)  # leave the caller's field where it is
    grid = field.grid
    if grid.num_voxels == 0:
        return empty_mesh()
    lattice = lattice_for_voxels(grid.voxel_coords(), grid.voxel_size, resolution)
    if lattice.dims.min() < 2:
        return empty_mesh()
    bricks = bricks_for_voxels(grid.voxel_coords(), grid.voxel_size, lattice, brick)
    all_verts, all_faces = brick_surfaces(field, lattice, bricks, brick, tau, culling, chunk, slab_points)
    n_verts = np.cumsum([0] + [len(v) for v in all_verts])
    all_faces = [f + n for f, n in zip(all_faces, n_verts)]
    if not all_faces:
        return empty_mesh()
    verts, faces = weld_vertices(np.concatenate(all_verts), np.concatenate(all_faces))
    if len(faces) == 0:
        return empty_mesh()
    mesh = coloured_mesh(field, lattice.origin[None] + verts * resolution, faces, tau, chunk)
    if culling is not None and culling.near_surface:
        mesh = cull_unobserved_faces(mesh, grid, tau, culling.dynamic_window, resolution)
    if culling is not None and culling.backfaces and camera_centres is not None:
        mesh = cull_backfaces(mesh, camera_centres)
    return mesh if len(mesh.faces) else empty_mesh()


@dataclass(frozen=True)
class DepthViews:
    """Depth frames a mesh is checked against (:func:`carve_free_space`): a run's stored keyframes
    (field time, depth, c2w pose) and the (3, 3) intrinsics of their depth."""

    views: Sequence[View]
    K: torch.Tensor

    def near(self, tau: float, window: float) -> list[View]:
        """The views within ``window`` (field time) of τ."""
        return [v for v in self.views if abs(float(v.tau) - float(tau)) <= window]


def free_space_votes(
    points: torch.Tensor, depth: torch.Tensor, c2w: torch.Tensor, K: torch.Tensor, margin: float = CARVE_MARGIN_M
) -> tuple[torch.Tensor, torch.Tensor]:
    """What one depth frame says about world points (N, 3): (N,) bool ``past``, it sees past the point
    (the nearest valid depth in the point's 3x3 pixel neighbourhood lies more than 3σ(z) + ``margin``
    behind it: free space there at that time; the nearest of the neighbourhood keeps a silhouette
    from seeing past the surface it bounds), and (N,) bool ``seen``, its depth there lies within
    3σ(z) + ``margin`` of the point. Points behind the camera, off the image or behind what it
    measured count as neither. depth: (H, W) metres, 0 = invalid; c2w: (4, 4); K: (3, 3)."""
    cam = transform_points(invert_pose(c2w.double()), points.double()).float()  # the pose in float64, the rest in float32
    z, inside, nearest, measured = depth_lookup(cam, depth.float(), K.float())
    tolerance = 3.0 * kinect_depth_sigma(z.clamp_min(0.0)) + margin
    past = inside & torch.isfinite(nearest) & (nearest > z + tolerance)
    seen = inside & (measured > 0) & ((measured - z).abs() <= tolerance)
    return past, seen


def carve_free_space(
    mesh: trimesh.Trimesh, observations: Sequence[tuple[torch.Tensor, torch.Tensor]], K: torch.Tensor, margin: float = CARVE_MARGIN_M
) -> trimesh.Trimesh:
    """``mesh`` without the faces that the depth frames ``observations`` ((H, W) depth, (4, 4) pose of
    the camera in the mesh's frame) see past (:func:`free_space_votes` at the face centres) more often
    than they see them: a surface the frames around the mesh time look through is not there at that
    time (a moving object the static map took in, where it used to be; a floater). Faces no frame
    sees stay."""
    if len(mesh.faces) == 0 or not observations:
        return mesh
    centres = torch.from_numpy(np.array(mesh.triangles_center, dtype=np.float64))
    past = torch.zeros(len(centres), dtype=torch.int32)
    seen = torch.zeros_like(past)
    K = K.cpu()
    for depth, pose in observations:
        p, s = free_space_votes(centres, depth.cpu(), pose.detach().cpu(), K, margin)
        past += p.int()
        seen += s.int()
    return keep_faces(mesh, ((past == 0) | (past <= seen)).numpy())


def mesh_at(
    field: TimeVaryingField, tau: float, cfg: MeshConfig, camera_centres: np.ndarray | None = None, cache: dict | None = None,
    depth_views: DepthViews | None = None,
) -> trimesh.Trimesh:
    """The scene's mesh at τ with ``cfg``'s resolution and culling (:func:`extract_mesh`).

    For an :class:`ObjectField`: the static field's mesh (meshed once into ``cache`` when the
    static field has no time) plus, for each object observed within its window of τ, the object
    field's mesh in its own frame (at ``field.mesh_resolution``; cached too when it has no time)
    placed by T_wo(τ) -- no sweep trails by construction. The static mesh without what the
    ``depth_views`` within ``cfg.carve_window`` of τ see past (:func:`carve_free_space`): the static
    scene is the same at every time, so what a frame near τ sees through is not there at τ. The
    objects' meshes are not carved: a deforming object differs between the frames' times and τ.
    """
    if not isinstance(field, ObjectField):
        return extract_mesh(field, tau, cfg.resolution, culling=cfg, camera_centres=camera_centres)
    cache = {} if cache is None else cache
    key = ("static", None if not field.time else float(tau))
    if key not in cache:
        with static_only(field):
            cache[key] = extract_mesh(field, tau, cfg.resolution, culling=cfg, camera_centres=camera_centres)
    near = [] if depth_views is None or cfg.carve_window is None else depth_views.near(tau, cfg.carve_window * field.time_scale)
    parts = [carve_free_space(cache[key], [(v.depth, v.pose) for v in near], depth_views.K) if near else cache[key]]
    own = MeshConfig(resolution=field.mesh_resolution, min_hits=cfg.min_hits, dynamic_window=None, near_surface=cfg.near_surface,
                     backfaces=False)  # cameras see an object from every side of its own frame
    for object_id, slot in field.slots.items():
        track = field.tracks.get(object_id)
        if track is None or not track.observed_near(tau, field.window):
            continue
        rel = float(tau) - slot.tau0
        okey = (object_id, rel if slot.field.time else None)
        if okey not in cache:
            cache[okey] = extract_mesh(slot.field, rel, own.resolution, culling=own)
        placed = cache[okey].copy()
        placed.apply_transform(track.pose_at(tau).double().numpy())
        parts.append(placed)
    parts = [m for m in parts if len(m.faces)]
    if not parts:
        return empty_mesh()
    return parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)


def save_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write a binary PLY atomically. An empty mesh is written as a valid PLY with no vertices, so a
    4D sequence has no gaps."""
    return atomic_write(path, trimesh.exchange.ply.export_ply(mesh, encoding="binary"))


def select_mesh_times(
    timestamps: Sequence[float], times: Sequence[float] | None = None, every: int | None = None
) -> list[float]:
    """Times to mesh, in seconds on the sequence clock.

    Args:
        timestamps: (N,) processed frames' timestamps, increasing, N >= 1.
        times: explicit times; each must lie in [first, last] (within ``TIME_TOLERANCE_S``, clamped).
        every: every k-th processed frame (k >= 1) instead.
    Returns:
        the times; by default the first and last timestamp (one when they coincide).
    Raises:
        ConfigError: both ``times`` and ``every``, a bad ``every``, or a time outside the range.
    """
    if not len(timestamps):
        raise ConfigError("the run records no processed frames (no timestamps to mesh at)")
    lo, hi = float(timestamps[0]), float(timestamps[-1])
    if times is not None and every is not None:
        raise ConfigError("give either mesh.times=[...] or every=k, not both")
    if every is not None:
        if int(every) != every or every < 1:
            raise ConfigError(f"every={every!r}: must be an integer >= 1")
        return [float(t) for t in timestamps[:: int(every)]]
    if times is None:
        return [lo] if hi == lo else [lo, hi]
    values = [float(t) for t in times]
    bad = [t for t in values if not lo - TIME_TOLERANCE_S <= t <= hi + TIME_TOLERANCE_S]
    if bad:
        raise ConfigError(f"mesh.times={bad}: outside the recorded range [{lo:.3f}, {hi:.3f}] s")
    return [min(max(t, lo), hi) for t in values]
