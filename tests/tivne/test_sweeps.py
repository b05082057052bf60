"""Sweeps: threads per job, the objective a sweeper minimises, and the Hydra plugins end to end in
smoke mode (joblib + Optuna in one sweep, submitit_local); the plugin tests skip without '.[sweep]'."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from tivne.cli import threads_per_job, usable_cores
from tivne.config import ConfigError, ObjectiveConfig
from tivne.evaluation.objective import objective_value
from tivne.reporting.runs import find_run_dirs, read_row, results_table

CONF = Path(__file__).resolve().parents[2] / "conf"
REPO = CONF.parent
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import Background  # noqa: E402

SMOKE = ["experiment=smoke", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null"]


def has_plugin(name: str) -> bool:
    return importlib.util.find_spec(f"hydra_plugins.{name}") is not None


needs_sweep = pytest.mark.skipif(
    not (has_plugin("hydra_joblib_launcher") and has_plugin("hydra_optuna_sweeper") and has_plugin("hydra_submitit_launcher")),
    reason="the sweep extra is not installed (pip install -e '.[sweep]')",
)


def train(logs: Path, *args: str) -> Background:
    """``python -m tivne.train <args>`` started in the background, its output in ``logs``.out / .err."""
    return Background([sys.executable, "-m", "tivne.train", *args], REPO, logs)


# ---- threads per job ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "launcher, cores, expected",
    [
        ({}, 8, None),  # the basic launcher: one job at a time, torch's default
        ({"n_jobs": 2}, 8, 4),
        ({"n_jobs": 3}, 8, 2),
        ({"n_jobs": 16}, 8, 1),
        ({"n_jobs": -1}, 8, 1),  # joblib: all cores, one job each
        ({"n_jobs": -2}, 8, 1),  # all but one: 7 jobs
        ({"n_jobs": -7}, 8, 4),  # 2 jobs
        ({"cpus_per_task": 6, "n_jobs": 2}, 8, 6),  # submitit / Slurm: the allocation
        ({"_target_": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher", "cpus_per_task": None}, 8, 1),
    ],
)
def test_threads_per_job(launcher, cores, expected):
    assert threads_per_job(launcher, cores) == expected


def test_a_run_outside_a_launcher_keeps_torch_default_threads():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=SMOKE)
    assert cfg.runtime.threads is None  # the resolver, outside a Hydra job
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        assert compose("config", overrides=[*SMOKE, "runtime.threads=3"]).runtime.threads == 3


# ---- the objective --------------------------------------------------------------------------------

METRICS = {"ate_rmse_m": 0.004, "object_chamfer_mean_m": 0.02, "s_per_frame": 1.5}


@pytest.mark.parametrize("metric, expected", [("ate", 0.004), ("chamfer", 0.02), ("s_per_frame", 1.5), ("weighted", 0.4 + 2.0 + 1.5)])
def test_objective_value(metric, expected):
    value, reason = objective_value(METRICS, ObjectiveConfig(metric=metric))
    assert value == pytest.approx(expected) and reason is None


def test_a_missing_metric_is_no_value_with_its_reason_never_a_number():
    value, reason = objective_value({"ate_rmse_m": None, "ate_reason": "no GT poses"}, ObjectiveConfig(metric="ate"))
    assert value is None and "no GT poses" in reason
    value, reason = objective_value({"ate_rmse_m": 0.01}, ObjectiveConfig(metric="chamfer"))
    assert value is None and "output.evaluate" in reason
    value, reason = objective_value({"ate_rmse_m": float("nan")}, ObjectiveConfig(metric="ate"))
    assert value is None


def test_weighted_leaves_out_terms_of_weight_zero():
    objective = ObjectiveConfig(metric="weighted", chamfer_weight=0, time_weight=0)
    assert objective_value({"ate_rmse_m": 0.01}, objective) == (pytest.approx(1.0), None)
    with pytest.raises(ConfigError, match="every weight is 0"):
        ObjectiveConfig(metric="weighted", ate_weight=0, chamfer_weight=0, time_weight=0)


def test_objective_presets_compose():
    for name in ("ate", "chamfer", "s_per_frame", "weighted"):
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            cfg = compose("config", overrides=[f"objective={name}"])
        assert ObjectiveConfig.from_mapping(dict(cfg.objective)).metric == name


# ---- the plugins, end to end ----------------------------------------------------------------------


@needs_sweep
def test_search_tracking_experiment_is_an_optuna_search():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=[smoke,search_tracking]"], return_hydra_config=True)
    sweeper = cfg.hydra.sweeper
    assert sweeper._target_.endswith("OptunaSweeper") and sweeper.direction == "minimize"
    assert set(sweeper.params) == {"odometry.levels", "odometry.outlier_sigmas", "mapping.iters"}
    assert sweeper.max_failure_rate == 1.0  # a failed trial is marked FAIL and the search goes on
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        slurm = compose("config", overrides=["hydra/launcher=slurm"], return_hydra_config=True).hydra.launcher
    assert slurm._target_.endswith("SlurmLauncher") and {"partition", "timeout_min", "cpus_per_task", "gpus_per_node"} <= set(slurm)


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory) -> dict[str, tuple[Path, Background]]:
    """The two plugin sweeps below, started together: each is mostly new interpreters importing torch
    and Lightning (the command, then its jobs), one core's work each, which two cores do side by side.
    {name: (sweep dir, process)}; each test waits for its own."""
    root = tmp_path_factory.mktemp("sweeps")
    sweep, local = root / "search", root / "local"
    optuna = train(root / "optuna", "-m", "hydra/sweeper=optuna", "hydra/sweeper/sampler=random", "hydra.sweeper.sampler.seed=0",
                     "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "hydra.sweeper.n_jobs=2", "hydra.sweeper.n_trials=2",
                     "hydra.sweeper.max_failure_rate=1.0", *SMOKE, "tracking.max_jump_m=choice(0.3,1e-9)", f"hydra.sweep.dir={sweep}")
    submitit = train(root / "submitit", "-m", "hydra/launcher=submitit_local", *SMOKE, "keyframe=random", f"hydra.sweep.dir={local}")
    procs = {"optuna": (sweep, optuna), "submitit": (local, submitit)}
    yield procs
    for _, started in procs.values():
        started.stop()


@needs_sweep
@pytest.mark.slow  # a subprocess and two joblib workers, each importing torch and Lightning (~15 s)
def test_optuna_on_joblib_runs_trials_side_by_side_and_marks_a_failed_trial(sweeps):
    """Two trials in one joblib batch: one tracks, one loses every frame (max_jump_m=1e-9); the best
    is the one that tracked, the failed one is a FAIL trial with its error in metrics.json. (The random
    sampler with seed 0 draws both values; the grid sampler of hydra-optuna-sweeper 1.3 crashes when
    the last trial of its grid fails.)"""
    sweep, started = sweeps["optuna"]
    out = started.finish(240)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "Failed experiment: error: 4 of 4 frames could not be tracked" in out.stderr + out.stdout
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_params"] == {"tracking.max_jump_m": 0.3} and 0 < best["best_value"] < 0.05
    rows = {r.overrides["tracking.max_jump_m"]: r for r in map(read_row, find_run_dirs([sweep]))}
    assert rows["0.3"].status == "complete" and rows["1e-09"].status == "failed"
    assert "could not be tracked" in rows["1e-09"].metrics["error"]
    assert {r.metrics["threads"] for r in rows.values()} == {max(1, usable_cores() // 2)}  # two jobs share the cores
    table = results_table(list(rows.values()))
    assert table.common["experiment"] == "smoke" and "tracking.max_jump_m" in table.columns


@needs_sweep
@pytest.mark.slow  # a subprocess and a submitit job (~12 s)
def test_submitit_local_runs_the_same_path(sweeps):
    sweep, started = sweeps["submitit"]
    out = started.finish(240)
    assert out.returncode == 0, out.stderr[-3000:]
    (run,) = find_run_dirs([sweep])
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["complete"] is True and metrics["frames"] == 5 and metrics["threads"] == 1
    assert (run / "trajectory.txt").is_file() and list((sweep / ".submitit").iterdir())
