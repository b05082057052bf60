"""The 4D mesh metrics (tivne.evaluation.surfaces) on analytic meshes of synthetic scenes with exact geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from skimage import measure

from data_modules.synthetic import SyntheticSequence
from tivne.config import MeshEvalSettings
from tivne.evaluation import GroundTruth
from tivne.evaluation.ground_truth import object_box, observed
from tivne.evaluation.surfaces import flatten_mesh_metrics, mesh_time_metrics, object_metrics
from tivne.metrics.surface import sample_mesh_surface

SMALL = dict(num_frames=4, fps=1.0, width=64, height=48, depth_noise=False, rgb_noise=0.0, cache_dir=None)
SETTINGS = MeshEvalSettings(pred_samples=20_000, object_samples=20_000, static_samples=5_000, window_s=0.0)
SPAN = (0.0, 3.0)
# fps=0.25: four frames over 12 s, long enough for the tumbling cube to show faces the first frame did not see.
CUBE_SPAN = (0.0, 12.0)


@pytest.fixture(scope="module")
def cube() -> SyntheticSequence:
    return SyntheticSequence(scene="cube", **{**SMALL, "fps": 0.25})


@pytest.fixture(scope="module")
def crossing() -> SyntheticSequence:
    return SyntheticSequence(scene="crossing", **SMALL)


def box_faces(gt: GroundTruth, t: float, name: str) -> list[trimesh.Trimesh]:
    """The six faces of object ``name``'s (box) surface at time t, each a 2-triangle mesh in the world frame."""
    box = object_box(gt, t, name)
    whole = trimesh.creation.box(extents=2 * box.half_extents)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = box.rotation, box.center
    whole.apply_transform(T)
    normals = np.round(whole.face_normals @ box.rotation, 6)  # in box axes: +-x, +-y, +-z
    return [whole.submesh([np.flatnonzero((normals == n).all(1))], append=True) for n in np.unique(normals, axis=0)]


def offset_surface(gt: GroundTruth, t: float, name: str, offset: float, step: float = 0.005) -> trimesh.Trimesh:
    """The level set ``sdf = offset`` around object ``name`` at time t: every point exactly ``offset`` from it."""
    box = object_box(gt, t, name)
    reach = np.abs(box.rotation).dot(box.half_extents) + offset + 3 * step  # world half extents of the rotated box
    lo = box.center - reach
    axes = [np.arange(lo[i], box.center[i] + reach[i], step) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sdf = gt.sdf(torch.from_numpy(pts), t, part="dynamic").numpy().reshape([len(a) for a in axes])
    v, f, _, _ = measure.marching_cubes(sdf, offset, spacing=(step,) * 3)
    return trimesh.Trimesh(v + lo, f, process=False)


def test_synthetic_sequence_is_ground_truth(cube):
    assert isinstance(cube, GroundTruth)
    assert not isinstance(object(), GroundTruth)


def test_completion_is_judged_on_the_observed_part(cube):
    """A mesh of exactly the cube faces some camera saw around t is complete over the observed part,
    though not over the whole cube; faces seen only later count once the window reaches them."""
    t = 0.0
    faces = box_faces(cube, t, "cube")
    seen = [observed(cube, sample_mesh_surface(f, 400, seed=1), t, 0.0, 0.0, "cube").any() for f in faces]
    assert 1 <= sum(seen) <= 3  # one camera sees at most three faces of a box
    mesh = trimesh.util.concatenate([f for f, s in zip(faces, seen) if s])
    samples = sample_mesh_surface(mesh, SETTINGS.pred_samples, seed=0)
    m = object_metrics(cube, t, "cube", mesh, samples, CUBE_SPAN, SETTINGS)
    assert m["cube_completion_ratio"] > 0.99 and m["cube_completion_m"] < 0.01
    assert m["cube_completion_ratio_whole"] < 0.8 and m["cube_observed_ratio"] < 0.7
    assert m["cube_accuracy_m"] < 1e-3 and m["cube_chamfer_m"] < 0.01 and "cube_reason" not in m
    # Over the whole sequence the cameras see more of the tumbling cube than the mesh holds.
    wide = object_metrics(cube, t, "cube", mesh, samples, CUBE_SPAN, MeshEvalSettings(**{**vars(SETTINGS), "window_s": 12.0}))
    assert wide["cube_observed_ratio"] > m["cube_observed_ratio"] and wide["cube_completion_ratio"] < 0.95
    # The whole cube is complete everywhere.
    whole = trimesh.util.concatenate(faces)
    full = object_metrics(cube, t, "cube", whole, sample_mesh_surface(whole, 20_000, seed=0), CUBE_SPAN, SETTINGS)
    assert full["cube_completion_ratio"] > 0.99 and full["cube_completion_ratio_whole"] > 0.99


def test_observed_window_is_clipped_to_the_processed_span(cube):
    t = 0.0
    pts = np.asarray(cube.sample_surface(t, 2000, part="dynamic", seed=0, name="cube"))
    alone = observed(cube, pts, t, t, t, "cube")
    assert np.array_equal(alone, cube.visible(torch.from_numpy(pts), t, 0.0, "cube").numpy())
    # [0, 12]: the frames at 0, 4, 8 and 12 s (the points are carried with the cube to the span's centre).
    everything = observed(cube, pts, t, 0.0, 12.0, "cube")
    assert np.array_equal(everything, cube.visible(torch.from_numpy(pts), t, 12.0, "cube").numpy())
    assert (everything >= alone).all() and everything.sum() > alone.sum()
    assert not observed(cube, pts, t, 9.0, 11.0, "cube").any()  # no frame in that span


def test_per_object_accuracy_and_chamfer_of_offset_surfaces(crossing):
    """Each object's mesh sits a known distance off its surface: 1 cm for one, 3 cm for the other."""
    t, offsets = 0.0, {"far": 0.01, "near": 0.03}
    parts = {name: offset_surface(crossing, t, name, d) for name, d in offsets.items()}
    mesh = trimesh.util.concatenate(list(parts.values()))
    settings = MeshEvalSettings(**{**vars(SETTINGS), "window_s": 3.0, "threshold_m": 0.02})
    m = mesh_time_metrics(crossing, t, mesh, SPAN, settings)
    for name, d in offsets.items():
        assert m[f"{name}_accuracy_m"] == pytest.approx(d, rel=0.03)
        assert m[f"{name}_completion_m"] == pytest.approx(d, rel=0.06)
        assert m[f"{name}_chamfer_m"] == pytest.approx(d, rel=0.05)
    assert m["far_completion_ratio"] > 0.97 and m["near_completion_ratio"] < 0.03  # threshold 2 cm
    # Every sample of the 3 cm surface is a ghost at 2 cm, none of the 1 cm one.
    share = parts["near"].area / mesh.area
    assert m["ghost_fraction"] == pytest.approx(share, abs=0.02)
    assert m["static_completion_ratio"] < 0.01 and m["static_accuracy_m"] is None  # no static surface in the mesh
    flat = flatten_mesh_metrics({t: m}, crossing.object_names, first=t)
    assert flat["mesh_t0.00_near_chamfer_m"] == m["near_chamfer_m"] == flat["near_chamfer_first_m"]
    assert flat["object_chamfer_max_m"] == m["near_chamfer_m"] and "near_chamfer_last_m" not in flat
    assert flat["object_chamfer_mean_m"] == pytest.approx(0.5 * (m["near_chamfer_m"] + m["far_chamfer_m"]))
    assert flat["ghost_fraction_max"] == m["ghost_fraction"] and "object_chamfer_reason" not in flat


def test_missing_object_and_empty_mesh_give_reasons(crossing):
    t = 0.0
    far_only = offset_surface(crossing, t, "far", 0.0)
    m = mesh_time_metrics(crossing, t, far_only, SPAN, MeshEvalSettings(**{**vars(SETTINGS), "window_s": 3.0}))
    assert m["near_accuracy_m"] is None and m["near_chamfer_m"] is None and "box" in m["near_reason"]
    assert m["near_completion_ratio"] == 0.0 and m["far_chamfer_m"] < 0.005
    flat = flatten_mesh_metrics({t: m}, crossing.object_names)
    assert flat["object_chamfer_max_m"] == m["far_chamfer_m"] and "near at t=0.00" in flat["object_chamfer_reason"]
    empty = mesh_time_metrics(crossing, t, trimesh.Trimesh(), SPAN, SETTINGS)
    assert empty["reason"] == "empty mesh" and empty["ghost_fraction"] is None and empty["far_accuracy_m"] is None
    flat = flatten_mesh_metrics({t: empty}, crossing.object_names)
    assert flat["ghost_fraction_max"] is None and flat["ghost_fraction_reason"] and flat["object_chamfer_mean_m"] is None
