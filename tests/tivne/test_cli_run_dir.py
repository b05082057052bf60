"""Post-run commands take a run dir as a user copies it: a sweep's job dir is named from its
overrides (``0_experiment=smoke,seed=0``), which Hydra's override grammar cannot parse unquoted;
:func:`tivne.cli.quote_run_dir` quotes it, and view / mesh / evaluate / report run on a real joblib
sweep's job dir as printed (the sweep and the four command lines in one worker process: tests/cli_worker.py)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser

from tivne.cli import quote_run_dir

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import run_commands  # noqa: E402


@pytest.mark.parametrize("path", [
    "multirun/2026-12-02_02-00-00/0_experiment=smoke,seed=0", "a b/c'd", "x\\y", "end\\", "a[1]=b{c}:d", "plain/path",
])
def test_quoted_run_dir_parses_back_to_the_path(path):
    arg = quote_run_dir(["prog", f"run_dir={path}"])[1]
    assert OverridesParser.create().parse_override(arg).value() == path


def test_other_arguments_and_quoted_values_are_left_alone():
    argv = ["prog", "every=3", "run_dir='already quoted'", "mesh.times=[1,2]"]
    assert quote_run_dir(argv) == argv


SWEEP = ["experiment=smoke", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null", "data.max_frames=4", "seed=0"]
# The job dir the sweep below prints: its number and its overrides (Hydra's override_dirname, sorted).
JOB = Path("multirun/sweep/0_data.max_frames=4,dataset.cache_dir=null,dataset.height=60,dataset.width=80,experiment=smoke,seed=0")


@pytest.mark.slow  # a joblib sweep of one tiny job, then four commands on its job dir, in one worker (~25 s)
@pytest.mark.skipif(importlib.util.find_spec("hydra_plugins.hydra_joblib_launcher") is None, reason="needs '.[sweep]'")
def test_post_run_commands_take_a_joblib_job_dir_as_printed(tmp_path):
    # The sweep and the commands on its job dir in one worker process (one interpreter start less):
    # the commands name the job dir the sweep will print, checked against the folder it made.
    arg = f"run_dir={JOB}"
    with_view = importlib.util.find_spec("rerun") is not None
    sweep, report, mesh, evaluate, *view = run_commands([
        ("tivne.train", ["-m", *SWEEP, "hydra/launcher=joblib", "hydra.launcher.n_jobs=1", "hydra.sweep.dir=multirun/sweep"]),
        ("tivne.report", [arg, "report.frames=1", "report.mesh_width=64"]),
        ("tivne.mesh", [arg, "mesh.resolution=0.1"]),
        ("tivne.evaluate", [arg, "settings.render_every=0", "settings.pred_samples=1000", "settings.object_samples=1000",
                            "settings.static_samples=1000"]),
        *([("tivne.view", [arg, "every=3", "mesh.resolution=0.1"])] if with_view else []),
    ], cwd=tmp_path)
    assert sweep.returncode == 0, sweep.stderr[-2000:]
    (job,) = [p.relative_to(tmp_path) for p in (tmp_path / "multirun" / "sweep").iterdir() if p.is_dir()]
    assert job == JOB and job.name.startswith("0_") and job.name.endswith("experiment=smoke,seed=0")  # what the user copies
    assert f"results in {tmp_path / JOB}" in sweep.stdout
    assert report.returncode == 0, report.stderr[-2000:]
    assert (tmp_path / job / "report.html").is_file()
    assert mesh.returncode == 0 and "faces=" in mesh.stdout, mesh.stderr[-2000:]
    assert evaluate.returncode == 0, evaluate.stderr[-2000:]
    assert json.loads(evaluate.stdout)["ate_rmse_m"] is not None
    if with_view:
        (view,) = view
        assert view.returncode == 0, view.stderr[-2000:]
        assert (tmp_path / job / "view.rrd").is_file() and "meshes=2" in view.stdout
