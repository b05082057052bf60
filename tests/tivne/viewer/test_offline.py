"""``tivne.view``'s recording of a finished cube run: one camera per frame equal to trajectory.txt,
the per-frame error plot, GT boxes, and the 4D mesh sequence on the time slider with the cube where
the ground truth has it at each mesh time (t = 0 and t = 2.5 s), not where it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

pytest.importorskip("rerun")

from data_modules.tables import read_tum_trajectory  # noqa: E402
from tivne.cli import run_sequence  # noqa: E402
from tivne.config import MeshConfig  # noqa: E402
from tivne.slam.run import run  # noqa: E402
from tivne.viewer import entities as E  # noqa: E402
from tivne.viewer.offline import record_run  # noqa: E402
from tivne.viewer.readback import mesh_of, pose_of, read_recording, rows_with  # noqa: E402

CONF_DIR = str(Path(__file__).resolve().parents[3] / "conf")

# 16 frames 1/6 s apart: t = 0 .. 2.5 s; the cube moves ~0.35 m, about twice its size.
CUBE = ["experiment=smoke", "dataset.width=120", "dataset.height=90", "dataset.cache_dir=null", "data.stride=5",
        "data.max_frames=16", "mesh.resolution=0.05"]


@pytest.fixture(scope="module", params=["tivne", "objects"])
def cube_run(tmp_path_factory, request):
    """The finished run, with the paper's field and with the object fields (whose mesh at t is the
    static mesh plus the cube's canonical mesh placed by its tracked pose)."""
    run_dir = tmp_path_factory.mktemp(f"cube-{request.param}")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[*CUBE, f"field={request.param}"])
    metrics = run(cfg, run_dir)
    assert metrics["frames"] == 16 and metrics["ate_rmse_m"] < 0.02
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")  # as Hydra does: tivne.view rebuilds the sequence from it
    return run_dir


def cube_vertices(world: np.ndarray, gt, t: float, margin: float = 0.05) -> np.ndarray:
    """(N, 3) world points -> (N,) bool: inside the cube's GT box at ``t`` dilated by ``margin``."""
    c, h, R = (np.asarray(x, dtype=np.float64) for x in gt.dynamic_box(t, "cube"))
    return (np.abs((world - c) @ R) <= h + margin).all(axis=1)


@pytest.mark.slow  # a 16-frame run and two meshes (~30 s)
def test_view_of_the_cube_run_has_the_cube_where_the_ground_truth_has_it(cube_run):
    view, _ = run_sequence(cube_run)
    summary = record_run(cube_run, view, every=15, mesh=MeshConfig(resolution=0.05))
    assert summary.path == cube_run / "view.rrd" and summary.frames == 16 and summary.error_frames == 16
    assert [t for t, _ in summary.meshes] == pytest.approx([0.0, 2.5])
    rows = read_recording(summary.path)

    ts, poses = read_tum_trajectory(cube_run / "trajectory.txt")
    cams = rows_with(rows["/" + E.CAMERA], "Transform3D:translation")
    assert [r.frame for r in cams] == list(range(16))
    assert [r.scene_time for r in cams] == pytest.approx([float(t - ts[0]) for t in ts], abs=1e-6)
    for r in cams:
        assert np.allclose(pose_of(r), poses[r.frame].numpy(), atol=1e-5)
    errors = rows_with(rows["/" + E.ERROR], "Scalars:scalars")
    assert len(errors) == 16 and max(r.values["Scalars:scalars"][0] for r in errors) < 0.05
    assert len(rows_with(rows[f"/{E.GT_OBJECTS}/cube"], "Boxes3D:half_sizes")) == 16

    gt = view.base
    meshes = rows_with(rows["/" + E.MESH], "Mesh3D:vertex_positions")
    assert [(r.frame, r.scene_time) for r in meshes] == [(0, 0.0), (15, pytest.approx(2.5))]
    to_world = np.asarray(gt.camera_pose(0), dtype=np.float64)  # the SLAM frame is the first camera's
    for row in meshes:
        t, other = row.scene_time, 2.5 - row.scene_time  # the cube's position at the other mesh time
        verts, _ = mesh_of(row)
        world = verts @ to_world[:3, :3].T + to_world[:3, 3]
        here = cube_vertices(world, gt, t)
        there = cube_vertices(world, gt, other) & ~here  # where the cube is at the other time, and not now
        assert here.sum() >= 100, f"t={t}: only {here.sum()} vertices where the cube is"
        error = gt.sdf(torch.as_tensor(world[here]), t, part="dynamic").abs().numpy()
        assert np.median(error) < 0.03, f"t={t}: the cube's surface is {np.median(error):.3f} m off"
        assert there.sum() < 0.25 * here.sum(), f"t={t}: {there.sum()} vertices where the cube is at t={other}"



@pytest.mark.slow  # one more mesh of the cube run
def test_a_recording_until_a_time_holds_the_frames_and_meshes_up_to_it(cube_run, tmp_path):
    view, _ = run_sequence(cube_run)
    summary = record_run(cube_run, view, every=15, mesh=MeshConfig(resolution=0.1), out=tmp_path / "first.rrd", until=1.0)
    assert summary.frames == 7 and [t for t, _ in summary.meshes] == [0.0]  # frames at t = 0, 1/6, ..., 1.0
    rows = read_recording(tmp_path / "first.rrd")
    assert max(r.scene_time for r in rows_with(rows["/" + E.CAMERA], "Transform3D:translation")) == pytest.approx(1.0)
