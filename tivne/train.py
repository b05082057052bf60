"""Entry point: ``python -m tivne.train dataset=cube field=tivne sampler=mask_weighted keyframe=overlap``.

The only place that reads the Hydra config of a training run: :func:`tivne.slam.run.run` checks
every section against :mod:`tivne.config` before any data is read, composes the loop and drives it.
It returns the ``objective`` (:mod:`tivne.evaluation.objective`), the value a sweeper minimises
(``-m hydra/sweeper=optuna``, see ``conf/experiment/search_tracking.yaml``). On the command line the
run-directory rules are checked before Hydra writes anything into the folder
(:class:`tivne.cli.RunDirGuard`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from data_modules.errors import overrides_checked
from tivne.cli import in_multirun, one_line_errors, register_defaults
from tivne.config import ObjectiveConfig
from tivne.evaluation.objective import objective_value
from tivne.slam.outputs import RunDir
from tivne.slam.run import plain, run
from tivne.utils import RunInterrupted

register_defaults()


# An absolute path: the same whether this module runs as __main__ or as tivne.train (below).
CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


@overrides_checked
@overrides_checked
@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> float | None:
    run_dir = HydraConfig.get().runtime.output_dir
    try:
        metrics = run(cfg, run_dir)
    except RunInterrupted as exc:
        way = "resume=true continues it" if RunDir(run_dir).checkpoint.is_file() else "no checkpoint was written; overwrite=true starts it again"
        print(f"interrupted by {exc}: partial results (complete: false) in {run_dir}; {way}", file=sys.stderr)
        sys.exit(exc.exit_code)
    keys = ["frames", "s_per_frame", "track_ms_per_iter", "map_ms_per_iter", "ate_rmse_m", "peak_rss_mb"]
    print(json.dumps({k: metrics.get(k) for k in keys}))
    print(f"results in {run_dir}")
    return sweep_value(metrics, ObjectiveConfig.from_mapping(plain(cfg.objective)))


def sweep_value(metrics: dict[str, Any], objective: ObjectiveConfig) -> float | None:
    """The objective to minimise; None (a failed Optuna trial, never a made-up number) with a
    warning when the run could not compute it."""
    value, reason = objective_value(metrics, objective)
    if value is None:
        note = ": this trial fails" if in_multirun() else ""
        print(f"warning: objective {objective.metric} not computable ({reason}){note}", file=sys.stderr)
    return value


if __name__ == "__main__":
    # Run the task function of the module tivne.train, not of __main__: a launcher that runs jobs in
    # other processes (joblib, submitit) pickles it, and one from __main__ would be pickled by value,
    # without the module's names.
    from tivne.train import main as task

    task()
