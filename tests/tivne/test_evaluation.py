"""Run evaluation (tivne.evaluation.evaluate_run and python -m tivne.evaluate) on hand-made run
directories over a tiny moving-cube sequence."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from skimage import measure

from data_modules.frame import Frame
from data_modules.sequence import SequenceDataset, SequenceView
from data_modules.synthetic import SyntheticSequence
from data_modules.tables import write_tum_trajectory
from tivne.config import ConfigError, MeshConfig, MeshEvalSettings
from tivne.evaluation import GroundTruth, evaluate_run, trajectory_metrics
from tivne.meshing import save_mesh
from tivne.slam.outputs import RunDir

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import Batch, used_in_module  # noqa: E402

# fps=1: the cube moves ~0.3 m between the first and last frame, so a stale mesh shows up.
CUBE_ARGS = dict(num_frames=4, fps=1.0, width=64, height=48, depth_noise=False, rgb_noise=0.0, cache_dir=None)
FAST = MeshEvalSettings(pred_samples=100_000, object_samples=10_000, static_samples=20_000, render_every=2)


@pytest.fixture(scope="module")
def view() -> SequenceView:
    return SequenceView(SyntheticSequence(**CUBE_ARGS))


class NoGeometry(SequenceDataset):
    """The frames of another sequence without any ground truth (as a recorded sequence)."""

    def __init__(self, source: SequenceDataset) -> None:
        self.source, self.name = source, "plain"
        self.intrinsics, self.timestamps = source.intrinsics, source.timestamps

    def load_frame(self, i: int) -> Frame:
        return replace(self.source[i], gt_pose=None, mask=None)


def gt_mesh(dataset: SyntheticSequence, t: float, step: float = 0.03) -> trimesh.Trimesh:
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


def make_run(run_dir: Path, view: SequenceView, meshes: dict[float, trimesh.Trimesh], frames: int | None = None) -> Path:
    """A run dir whose trajectory is the GT (in the first camera's frame; the first ``frames``
    frames) and whose meshes are given in world."""
    poses = torch.stack([view.base.camera_pose(int(i)) for i in view.source_indices])[:frames]
    slam_from_world = torch.linalg.inv(poses[0])
    write_tum_trajectory(run_dir / "trajectory.txt", view.timestamps[: len(poses)], slam_from_world @ poses)
    for t, mesh in meshes.items():
        slam_mesh = mesh.copy()
        slam_mesh.apply_transform(slam_from_world.numpy())
        save_mesh(slam_mesh, RunDir(run_dir).mesh_path(t))
    return run_dir


def save_sphere_checkpoint(run_dir: Path, view: SequenceView) -> None:
    """A checkpoint of a 0.3 m sphere field (nothing like the cube scene) over the view's frames."""
    from test_meshing import embedded_sphere, outside_cameras  # same folder (pytest prepends it to sys.path)

    from tivne.field.clock import Clock
    from tivne.slam.checkpoint import save_checkpoint

    save_checkpoint(RunDir(run_dir).checkpoint, embedded_sphere(True), list(view.timestamps), outside_cameras(len(view)), Clock(0.0))


def test_perfect_run_scores_perfectly(tmp_path, view, gt_meshes):
    run_dir = make_run(tmp_path, view, gt_meshes)
    m = evaluate_run(run_dir, view, settings=FAST)
    assert m["ate_rmse_m"] < 1e-5 and m["ate_max_m"] < 1e-5 and m["ate_frames"] == 4 and m["ate_partial"] is False
    for label in ("first", "last"):
        assert m[f"cube_accuracy_{label}_m"] < 0.01 and m[f"cube_chamfer_{label}_m"] < 0.01
        assert m[f"cube_completion_ratio_{label}"] > 0.99
        assert m[f"ghost_fraction_{label}"] < 0.005
        assert m[f"static_completion_ratio_{label}"] > 0.99
        assert m[f"static_accuracy_{label}_m"] < 0.01
    assert m["mesh_t0.00_cube_accuracy_m"] == m["cube_accuracy_first_m"]
    assert m["mesh_t3.00_ghost_fraction"] == m["ghost_fraction_last"] <= m["ghost_fraction_max"]
    assert m["object_chamfer_max_m"] < 0.01 and m["object_chamfer_mean_m"] <= m["object_chamfer_max_m"]
    assert m["mesh_eval_frame"] == "first_camera" and m["mesh_eval_times"] == [0.0, 3.0] and m["mesh_eval_window_s"] == 0.5
    assert m["psnr_db"] is None and m["ssim"] is None and "checkpoint" in m["psnr_reason"] == m["ssim_reason"]  # nothing to render
    json.dumps(m, allow_nan=False)  # JSON-serialisable, no NaN

    ate_frame = evaluate_run(run_dir, view, settings=FAST, frame="ate")
    assert ate_frame["cube_accuracy_last_m"] == pytest.approx(m["cube_accuracy_last_m"], abs=2e-3)
    one = evaluate_run(run_dir, view, MeshConfig(times=(3.0,)), settings=FAST)
    assert "cube_accuracy_last_m" in one and "cube_accuracy_first_m" not in one  # summaries only of times evaluated


def test_stale_cube_is_a_ghost(tmp_path, view, gt_meshes):
    first, last = sorted(gt_meshes)
    run_dir = make_run(tmp_path, view, {first: gt_meshes[first], last: gt_meshes[first]})
    m = evaluate_run(run_dir, view, settings=FAST)
    assert m["ghost_fraction_first"] < 0.005 and m["ghost_fraction_last"] > 0.005
    assert m["ghost_fraction_max"] == m["ghost_fraction_last"]
    assert m["cube_completion_ratio_last"] < 0.9 and m["cube_chamfer_last_m"] > 0.02
    assert m["static_completion_ratio_last"] > 0.99  # the background is still right


def test_checkpoint_meshes_images_and_reasons(tmp_path, view):
    make_run(tmp_path, view, {})
    save_sphere_checkpoint(tmp_path, view)
    m = evaluate_run(tmp_path, view, MeshConfig(resolution=0.05), settings=FAST)
    # A 0.3 m sphere around the first camera: nothing near the cube, all of it ghost.
    assert m["cube_accuracy_first_m"] is None and "box" in m["mesh_t0.00_cube_reason"] == m["cube_accuracy_first_reason"]
    assert m["cube_completion_ratio_first"] == 0.0 and m["ghost_fraction_first"] == 1.0
    assert 0 <= m["static_completion_ratio_last"] < 0.05
    assert "cube at t=0.00" in m["object_chamfer_reason"]
    # Re-rendered frames 0 and 2 (render_every=2) at the checkpoint's poses.
    assert m["psnr_frames"] == 2 and 0 < m["psnr_db"] < 60 and -1 <= m["ssim"] <= 1 and m["mse"] > 0
    none = evaluate_run(tmp_path, view, MeshConfig(resolution=0.05), settings=replace(FAST, render_every=0))
    assert "psnr_db" not in none and "render_every" in none["psnr_reason"]


def test_dataset_without_ground_truth(tmp_path, view):
    plain = NoGeometry(view.base)
    assert isinstance(view.base, GroundTruth) and not isinstance(plain, GroundTruth)
    m = evaluate_run(tmp_path, plain)  # an empty run dir: reasons, nothing raised
    assert m["ate_rmse_m"] is None and "trajectory.txt" in m["ate_reason"]
    assert "no ground-truth geometry" in m["mesh_eval_reason"] and "checkpoint" in m["psnr_reason"]
    make_run(tmp_path, view, {})
    save_sphere_checkpoint(tmp_path, view)
    m = evaluate_run(tmp_path, plain, settings=FAST)
    assert "ground-truth" in m["ate_reason"] and "no ground-truth geometry" in m["mesh_eval_reason"]
    assert m["psnr_frames"] == 2 and m["psnr_db"] > 0  # images need no ground truth
    assert m["psnr_dynamic_db"] is None and m["psnr_dynamic_reason"]
    metrics, result = trajectory_metrics(np.arange(3.0), np.tile(np.eye(4), (3, 1, 1)), np.zeros(0), np.zeros((0, 4, 4)))
    assert result is None and metrics["ate_rmse_m"] is None and "ground-truth" in metrics["ate_reason"]


def test_mesh_times_outside_the_run_are_refused(tmp_path, view, gt_meshes):
    run_dir = make_run(tmp_path, view, gt_meshes)
    with pytest.raises(ConfigError, match=r"outside the recorded range \[0.000, 3.000\]"):
        evaluate_run(run_dir, view, MeshConfig(times=(1.0, 99.0)), settings=FAST)
    with pytest.raises(ConfigError, match="no processed frames"):
        evaluate_run(tmp_path / "meshes", view, MeshConfig(times=(1.0,)))  # a directory without a run


def test_partial_run_is_flagged(tmp_path, view, gt_meshes):
    run_dir = make_run(tmp_path, view, {}, frames=3)
    m = evaluate_run(run_dir, view, settings=FAST)
    assert m["ate_partial"] is True and m["ate_frames"] == 3 and m["sequence_frames"] == 4
    assert m["mesh_eval_times"] == [0.0, 2.0]  # the recorded range: what the run reached
    (tmp_path / "full").mkdir()
    full = make_run(tmp_path / "full", view, {})
    assert evaluate_run(full, view, settings=FAST)["ate_partial"] is False
    RunDir(full).merge_metrics({"complete": False})  # stopped in the final pass
    assert evaluate_run(full, view, settings=FAST)["ate_partial"] is True


@pytest.fixture(scope="module", autouse=True)
def cli_started(request, tmp_path_factory) -> Iterator[tuple[Path, Batch] | None]:
    """The command lines of test_cli_merges_into_metrics_json on a run dir of its own, in one worker
    process (tests/cli_worker.py), started with the module's first test: its start (~10 s of one
    core importing torch and Lightning) and its evaluation overlap the in-process tests before it.
    A refusal whose stderr must be exactly one line goes first: it starts with nothing imported, as
    a new process does."""
    if not used_in_module(request, "cli"):
        yield None
        return
    tmp_path = tmp_path_factory.mktemp("evaluate_cli")
    run_dir = make_run(tmp_path, request.getfixturevalue("view"), request.getfixturevalue("gt_meshes"))
    overrides = ["experiment=smoke", "data.max_frames=null", "data.resize=null"] + [f"dataset.{k}={'null' if v is None else v}" for k, v in CUBE_ARGS.items()]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    (run_dir / "metrics.json").write_text(json.dumps({"frames": 4, "wall_s": 1.5}))
    fast = [f"settings.{k}={v}" for k, v in vars(FAST).items()]
    batch = Batch([
        ("tivne.evaluate", [f"run_dir={tmp_path / 'missing'}"]),
        ("tivne.evaluate", [f"run_dir={run_dir}", *fast]),
        ("tivne.evaluate", [f"run_dir={run_dir}", "mesh.times=[99]"]),  # refused; the good summaries stay
    ], cwd=REPO, watch=[run_dir / "metrics.json"])
    yield run_dir, batch
    batch.stop()


@pytest.fixture(scope="module")
def cli(cli_started) -> tuple[Path, list[subprocess.CompletedProcess]]:
    run_dir, batch = cli_started
    return run_dir, batch.results()


def test_cli_merges_into_metrics_json(cli):
    run_dir, (missing, out, refused) = cli
    assert out.returncode == 0, out.stderr[-2000:]
    on_disk = json.loads(out.files[run_dir / "metrics.json"])
    assert on_disk["frames"] == 4 and on_disk["wall_s"] == 1.5  # kept
    assert on_disk["ate_rmse_m"] < 1e-5 and on_disk["cube_completion_ratio_last"] > 0.99
    assert json.loads(out.stdout)["ate_rmse_m"] == on_disk["ate_rmse_m"]

    assert refused.returncode == 2 and refused.stderr.startswith("error: mesh.times=[99.0]") and len(refused.stderr.strip().splitlines()) == 1
    assert json.loads(refused.files[run_dir / "metrics.json"]) == on_disk

    assert missing.returncode == 2 and missing.stderr.startswith("error:") and len(missing.stderr.strip().splitlines()) == 1
