"""Smoke runs of the real composed config: every field x sampler x keyframe combination, CLI, errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from data_modules.tables import read_tum_trajectory
from tivne.config import ConfigError, MeshEvalSettings
from tivne.slam.checkpoint import load_checkpoint
from tivne.slam.run import run

CONF = Path(__file__).resolve().parents[2] / "conf"
# The cube rendered at 160x120, not its 640x480 (which costs ~1 s a run to render): the smoke runs still
# shrink it to their 80x60 (data.resize), and nothing below but the object fields' ghost fraction (whose
# test renders the full size) depends on the frame size.
BASE = ["experiment=smoke", "dataset.cache_dir=null", "output.image_every=2", "dataset.width=160", "dataset.height=120"]
FULL_SIZE = ["dataset.width=640", "dataset.height=480"]
sys.path.insert(0, str(CONF.parent / "tests"))
from cli_worker import Batch, used_in_module  # noqa: E402

# The run's final evaluation (output.evaluate=true) with fewer surface samples than the defaults (200k
# on the mesh, 50k per object, 100k static: ~20 s of nearest-neighbour queries per 5-frame run on
# 2 cores, against ~2 s; the metrics agree to ~1 mm). These tests check what a run evaluates and
# writes, not the estimates' noise; every other setting (render_every, threshold, window) is the default.
FAST_EVALUATION = MeshEvalSettings(pred_samples=100_000, object_samples=10_000, static_samples=20_000)


@pytest.fixture
def fast_evaluation(monkeypatch):
    from tivne.evaluation import evaluate_run

    def evaluate(*args, **kwargs):
        return evaluate_run(*args, **kwargs, settings=FAST_EVALUATION)  # a run that chose its own settings fails here

    monkeypatch.setattr("tivne.slam.run.evaluate_run", evaluate)


def compose_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=[*BASE, *overrides])


@pytest.mark.parametrize("field", ["tivne", "static"])
@pytest.mark.parametrize("sampler", ["uniform", "mask_weighted"])
@pytest.mark.parametrize("keyframe", ["overlap", "random"])
def test_every_combination_runs(tmp_path, field, sampler, keyframe):
    cfg = compose_cfg(f"field={field}", f"sampler={sampler}", f"keyframe={keyframe}", "keyframe.every=2", "keyframe.window=1")
    metrics = run(cfg, tmp_path)
    ts, poses = read_tum_trajectory(tmp_path / "trajectory.txt")
    assert len(ts) == 5 and metrics["frames"] == 5
    assert math.isfinite(metrics["s_per_frame"]) and metrics["s_per_frame"] > 0
    assert metrics["ate_rmse_m"] is not None and metrics["ate_rmse_m"] < 0.05
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk["frames"] == 5 and on_disk["complete"] is True
    assert (tmp_path / "checkpoints" / "slam.pt").is_file()
    field_back, meta = load_checkpoint(tmp_path / "checkpoints" / "slam.pt")
    assert field_back.time == (field == "tivne") and len(meta["timestamps"]) == 5
    assert len(list((tmp_path / "meshes").glob("*.ply"))) == 2
    assert list((tmp_path / "tb").glob("events.*"))


def test_run_takes_a_provider_object(tmp_path):
    from tivne.masks.base import DatasetMasks, RecordingMasks

    rec = RecordingMasks(DatasetMasks())  # replaces the configured masks=none
    metrics = run(compose_cfg("masks=none", "output.image_every=0"), tmp_path, masks=rec)
    assert metrics["frames"] == 5 and sorted(rec.masks) == [0, 1, 2, 3, 4]
    assert all(rec.masks[i] is not None and torch.equal(rec.masks[i], rec.gt[i]) for i in rec.masks)


def test_no_masks_runs(tmp_path):
    metrics = run(compose_cfg("masks=none"), tmp_path)
    assert metrics["frames"] == 5 and math.isfinite(metrics["s_per_frame"])
    assert len(read_tum_trajectory(tmp_path / "trajectory.txt")[0]) == 5
    assert (tmp_path / "checkpoints" / "slam.pt").is_file()


def test_presets_compose(tmp_path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        default = compose("config")
        fast, quality, paper = (compose("config", overrides=[f"experiment={e}"]) for e in ("fast", "quality", "paper"))
    assert (default.mapping.every, default.mapping.iters, default.mapping.rays) == (1, 5, 512) and default.tracking.method == "odometry"
    assert fast.mapping.iters == 3 and (quality.mapping.every, quality.mapping.iters, quality.mapping.rays) == (1, 20, 1024)
    assert default.render.n_band == 8 and quality.render.n_band == 12  # quality samples the band around the depth more densely
    assert paper.tracking.method == "field" and paper.mapping.every == 1 and paper.mapping.iters == 20 and paper.field_tracking.iters == 30
    smoke = compose_cfg("mapping.every=2", "data.max_frames=5", "masks=geometric")
    metrics = run(smoke, tmp_path)
    assert metrics["frames"] == 5 and metrics["map_ms_per_iter"] > 0
    assert len(read_tum_trajectory(tmp_path / "trajectory.txt")[0]) == 5


def test_final_evaluation_writes_4d_metrics(tmp_path, fast_evaluation):
    cfg = compose_cfg("output.evaluate=true", "mesh.times=[0.0,0.1]")
    metrics = run(cfg, tmp_path)
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk["mesh_eval_times"] == [0.0, 0.1] and on_disk["ate_partial"] is False
    for key in ("mesh_t0.10_cube_accuracy_m", "mesh_t0.10_cube_chamfer_m", "mesh_t0.10_ghost_fraction", "object_chamfer_max_m"):
        assert key in on_disk and key in metrics
    assert on_disk["psnr_frames"] == 1 and math.isfinite(on_disk["psnr_db"]) and on_disk["ssim"] is not None
    assert (tmp_path / "meshes" / "mesh_t0.100.ply").is_file()
    with pytest.raises(ConfigError, match="outside the recorded range"):  # before any frame is processed
        run(compose_cfg("mesh.times=[99]"), tmp_path / "refused")
    assert not (tmp_path / "refused").exists()


@pytest.mark.parametrize("tracks", ["tracked", "oracle"])
def test_object_fields_run_on_their_tracks_and_come_back_from_the_checkpoint(tmp_path, tracks, fast_evaluation):
    from tivne.field.objects import ObjectField

    # Full-size frames: at 160x120 the ghost fraction is ~0.08 (0.036 at 640x480), over the 0.05 checked below.
    cfg = compose_cfg(*FULL_SIZE, "field=objects", f"object_field.tracks={tracks}", "output.evaluate=true", "mesh.times=[0.0,0.1]")
    metrics = run(cfg, tmp_path)
    field, _ = load_checkpoint(tmp_path / "checkpoints" / "slam.pt")
    assert isinstance(field, ObjectField) and not field.time and list(field.slots) == [1]
    assert (tmp_path / "objects" / "1.txt").is_file()  # field=objects turns the object tracker on (with the oracle too: its error is reported)
    assert field.slots[1].field.grid.num_voxels > 0 and field.grid.dynamic_keys.numel() == 0  # the cube lives in its own grid
    assert metrics["mesh_t0.10_cube_chamfer_m"] < 0.05 and metrics["ghost_fraction_max"] < 0.05


def test_object_fields_without_the_object_tracker_are_refused_before_the_run(tmp_path):
    with pytest.raises(ConfigError, match="set objects.track=true"):
        run(compose_cfg("field=objects", "objects.track=false"), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_overwrite_clears_the_old_results_first(tmp_path):
    run(compose_cfg("mesh.times=[0.0,0.1]"), tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    (tmp_path / "metrics.json").write_text(json.dumps(metrics | {"stale_key": 1}))
    old_meshes = sorted(p.name for p in (tmp_path / "meshes").iterdir())
    from tivne.slam.outputs import RunDirError

    with pytest.raises(RunDirError, match="already holds results"):
        run(compose_cfg(), tmp_path)
    assert json.loads((tmp_path / "metrics.json").read_text())["stale_key"] == 1  # refused: nothing touched
    old_events = {p.name for p in (tmp_path / "tb").glob("events.*")}
    metrics = run(compose_cfg("overwrite=true", "output.image_every=0"), tmp_path)
    assert "stale_key" not in json.loads((tmp_path / "metrics.json").read_text()) and metrics["complete"] is True
    meshes = sorted(p.name for p in (tmp_path / "meshes").iterdir())
    assert old_meshes == ["mesh_t0.000.ply", "mesh_t0.100.ply"] and meshes == ["mesh_t0.000.ply", "mesh_t0.133.ply"]
    new_events = {p.name for p in (tmp_path / "tb").glob("events.*")}
    assert old_events and new_events and not old_events & new_events  # the old run's events went too


# ---- the command line (last: its worker, started with the module's first test, runs alongside the runs above) --------


def unusable_depth_sequence(seq: Path) -> None:
    """A folder sequence of 6 frames whose depth is 0 everywhere (random colour)."""
    import cv2
    import numpy as np

    for sub in ("rgb", "depth"):
        (seq / sub).mkdir(parents=True)
    gen = np.random.default_rng(0)
    for i in range(6):
        cv2.imwrite(str(seq / "rgb" / f"{i:06d}.png"), gen.integers(0, 255, (60, 80, 3), dtype=np.uint8))
        cv2.imwrite(str(seq / "depth" / f"{i:06d}.png"), np.zeros((60, 80), np.uint16))
    (seq / "intrinsics.txt").write_text("60 60 39.5 29.5\n")


@pytest.fixture(scope="module", autouse=True)
def cli_started(request, tmp_path_factory) -> Iterator[tuple[Path, list[str], Batch] | None]:
    """The command lines of the CLI tests below, in one worker process (tests/cli_worker.py): one
    interpreter start instead of four. Started with the module's first test, so its start (~10 s
    of one core importing torch and Lightning) and runs overlap the in-process runs before the CLI
    tests. The refusal whose stderr is checked line by line goes first: it starts with nothing
    imported, as a new process does."""
    if not used_in_module(request, "cli"):
        yield None
        return
    root = tmp_path_factory.mktemp("train_cli")
    (root / "refused").mkdir()
    unusable_depth_sequence(root / "seq")
    commands = {
        "bad value": [*BASE, "dataset.num_frames=0", f"hydra.run.dir={root / 'refused'}"],
        "no depth": ["experiment=smoke", "dataset=folder", f"dataset.root={root / 'seq'}", "masks=none", f"hydra.run.dir={root / 'run'}"],
        "single": [*BASE, f"hydra.run.dir={root / 'one'}"],
        "multirun": ["-m", *BASE, "field.time=true,false", f"hydra.sweep.dir={root / 'sweep'}"],
    }
    batch = Batch([("tivne.train", args) for args in commands.values()], cwd=root)
    yield root, list(commands), batch
    batch.stop()


@pytest.fixture(scope="module")
def cli(cli_started) -> tuple[Path, dict[str, subprocess.CompletedProcess]]:
    """The CLI tests' results (waits for the worker)."""
    root, names, batch = cli_started
    return root, dict(zip(names, batch.results()))


def test_cli_single_run_and_multirun(cli):
    root, outs = cli
    out = outs["single"]
    assert out.returncode == 0, out.stderr[-2000:]
    assert (root / "one" / "trajectory.txt").is_file() and (root / "one" / ".hydra" / "config.yaml").is_file()
    out = outs["multirun"]
    assert out.returncode == 0, out.stderr[-2000:]
    assert len(list((root / "sweep").glob("*/trajectory.txt"))) == 2


def test_bad_dataset_value_is_one_error_line(cli):
    out = cli[1]["bad value"]
    assert out.returncode == 2
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "num_frames" in errors[0]
    assert "Traceback" not in out.stderr


def test_a_run_without_usable_depth_fails_with_one_line_not_an_identity_trajectory(cli):
    root, outs = cli
    out = outs["no depth"]
    assert out.returncode == 3, out.stderr[-2000:]
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "could not be tracked" in errors[0] and "Traceback" not in out.stderr
    assert sum(line.startswith("warning: frame") for line in out.stderr.splitlines()) == 4
    metrics = json.loads((root / "run" / "metrics.json").read_text())
    assert metrics["frames_without_tracking"] == 4  # written before the refusal
