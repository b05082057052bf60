"""Run evaluation on hand-made run directories over a tiny moving-cube sequence."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from skimage import measure

from data_modules.sequence import SequenceView
from data_modules.synthetic import SyntheticSequence as MovingCubeSequence
from data_modules.tables import write_tum_trajectory
from tivne.cli import register_defaults
from tivne.config import MeshEvalSettings
from tivne.evaluation import (
    evaluate_run,
    flatten_mesh_metrics,
    in_boxes,
    trajectory_metrics,
)
from tivne.meshing import save_mesh
from tivne.slam.outputs import RunDir

REPO = Path(__file__).resolve().parents[2]
# fps=1: the cube moves ~0.3 m between the first and last frame, so a stale mesh shows up.
CUBE_ARGS = dict(num_frames=4, fps=1.0, width=64, height=48, depth_noise=False, rgb_noise=0.0, cache_dir=None)
FAST = MeshEvalSettings(pred_samples=100_000, gt_samples=60_000, dynamic_samples=10_000, static_every=2, static_per_frame=2_000)


@pytest.fixture(scope="module")
def view() -> SequenceView:
    return SequenceView(MovingCubeSequence(**CUBE_ARGS))


def gt_mesh(dataset: MovingCubeSequence, t: float, step: float = 0.03) -> trimesh.Trimesh:
    """Marching cubes of the exact scene SDF at time t (world frame): the visible GT surface."""
    lo = np.array(dataset.room_min) - 2 * step
    hi = np.array(dataset.room_max) + 2 * step
    axes = [np.arange(lo[i], hi[i] + step, step) for i in range(3)]
    pts = torch.from_numpy(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3))
    sdf = dataset.sdf(pts, t).numpy().reshape([len(a) for a in axes])
    v, f, _, _ = measure.marching_cubes(sdf, 0.0, spacing=(step,) * 3)
    return trimesh.Trimesh(v + lo, f, process=False)


@pytest.fixture(scope="module")
def gt_meshes(view) -> dict[float, trimesh.Trimesh]:
    ts = view.timestamps
    return {float(t): gt_mesh(view.base, float(t)) for t in (ts[0], ts[-1])}


def make_run(run_dir: Path, view: SequenceView, meshes: dict[float, trimesh.Trimesh]) -> Path:
    """A run dir whose trajectory is the GT (in the first camera's frame) and whose meshes are given in world."""
    poses = torch.stack([view.base.camera_pose(int(i)) for i in view.source_indices])
    slam_from_world = torch.linalg.inv(poses[0])
    write_tum_trajectory(run_dir / "trajectory.txt", view.timestamps, slam_from_world @ poses)
    for t, mesh in meshes.items():
        slam_mesh = mesh.copy()
        slam_mesh.apply_transform(slam_from_world.numpy())
        save_mesh(slam_mesh, RunDir(run_dir).mesh_path(t))
    return run_dir


def test_perfect_run_scores_perfectly(tmp_path, view, gt_meshes):
    run_dir = make_run(tmp_path, view, gt_meshes)
    m = evaluate_run(run_dir, dataset_view=view, settings=FAST)
    assert m["ate_rmse_m"] < 1e-5 and m["ate_max_m"] < 1e-5 and m["ate_frames"] == 4
    for label in ("first", "last"):
        assert m[f"cube_accuracy_{label}_m"] < 0.01
        assert m[f"cube_completion_ratio_{label}"] > 0.99
        assert m[f"ghost_fraction_{label}"] < 0.005
        assert m[f"static_completion_ratio_{label}"] > 0.99
        assert m[f"static_accuracy_{label}_m"] < 0.01
    assert m["mesh_t0.00_cube_accuracy_m"] == m["cube_accuracy_first_m"]
    assert m["mesh_t3.00_ghost_fraction"] == m["ghost_fraction_last"]
    assert m["mesh_eval_frame"] == "first_camera"
    json.dumps(m, allow_nan=False)  # JSON-serialisable, no NaN

    ate_frame = evaluate_run(run_dir, dataset_view=view, settings=FAST, frame="ate")
    assert ate_frame["cube_accuracy_last_m"] == pytest.approx(m["cube_accuracy_last_m"], abs=2e-3)


def test_stale_cube_is_a_ghost(tmp_path, view, gt_meshes):
    first, last = sorted(gt_meshes)
    run_dir = make_run(tmp_path, view, {first: gt_meshes[first], last: gt_meshes[first]})
    m = evaluate_run(run_dir, dataset_view=view, settings=FAST)
    assert m["ghost_fraction_first"] < 0.005 and m["ghost_fraction_last"] > 0.005
    assert m["cube_completion_ratio_last"] < 0.9
    assert m["static_completion_ratio_last"] > 0.99  # the background is still right


def test_mesh_from_checkpoint_and_reasons(tmp_path, view):
    from test_meshing import (  # same folder (pytest prepends it to sys.path)
        embedded_sphere,
        field_kwargs,
        outside_cameras,
    )

    from tivne.slam.checkpoint import save_checkpoint

    make_run(tmp_path, view, {})
    save_checkpoint(tmp_path / "checkpoints" / "slam.pt", embedded_sphere(True), field_kwargs(True),
                    list(view.timestamps), outside_cameras(4), t0=0.0)
    m = evaluate_run(tmp_path, dataset_view=view, mesh_resolution=0.05, settings=FAST)
    # A 0.3 m sphere around the first camera: nothing near the cube, all of it ghost.
    assert m["cube_accuracy_first_m"] is None and "box" in m["mesh_t0.00_cube_reason"]
    assert m["cube_completion_ratio_first"] == 0.0 and m["ghost_fraction_first"] == 1.0
    assert 0 <= m["static_completion_ratio_last"] < 0.05


def test_no_ground_truth():
    class Plain:
        name = "plain"
        has_gt_poses = False
        timestamps = np.arange(3.0)

    # No trajectory file and no GT: reasons, nothing raised.
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        m = evaluate_run(d, dataset_view=Plain())
    assert m["ate_rmse_m"] is None and "trajectory.txt" in m["ate_reason"]
    assert "no ground-truth geometry" in m["mesh_eval_reason"]
    metrics, result = trajectory_metrics(np.arange(3.0), np.tile(np.eye(4), (3, 1, 1)), np.zeros(0), np.zeros((0, 4, 4)))
    assert result is None and metrics["ate_rmse_m"] is None and "ground-truth" in metrics["ate_reason"]


def test_helpers():
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.3, 0.0, 0.0]])
    box = (np.zeros(3), np.full(3, 0.1), np.eye(3))
    assert in_boxes(pts, [box], margin=0.15).tolist() == [True, True, False]
    flat = flatten_mesh_metrics({1.0: {"cube_accuracy_m": 0.1, "ghost_fraction": 0.2}}, 1.0, 2.0)
    assert flat["mesh_t1.00_cube_accuracy_m"] == 0.1 and flat["cube_accuracy_first_m"] == 0.1
    assert flat["ghost_fraction_last"] is None


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tivne.evaluate", *args], capture_output=True, text=True, timeout=300, cwd=REPO)


def test_cli_merges_into_metrics_json(tmp_path, view, gt_meshes):
    run_dir = make_run(tmp_path, view, gt_meshes)
    register_defaults()
    overrides = ["experiment=smoke", "data.max_frames=null", "data.resize=null"] + [f"dataset.{k}={'null' if v is None else v}" for k, v in CUBE_ARGS.items()]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    (run_dir / "metrics.json").write_text(json.dumps({"frames": 4, "wall_s": 1.5}))
    fast = [f"settings.{k}={v}" for k, v in vars(FAST).items()]
    out = run_cli(f"run_dir={run_dir}", *fast)
    assert out.returncode == 0, out.stderr[-2000:]
    on_disk = json.loads((run_dir / "metrics.json").read_text())
    assert on_disk["frames"] == 4 and on_disk["wall_s"] == 1.5  # kept
    assert on_disk["ate_rmse_m"] < 1e-5 and on_disk["cube_completion_ratio_last"] > 0.99
    assert json.loads(out.stdout)["ate_rmse_m"] == on_disk["ate_rmse_m"]

    out = run_cli(f"run_dir={tmp_path / 'missing'}")
    assert out.returncode == 2 and out.stderr.startswith("error:") and len(out.stderr.strip().splitlines()) == 1
