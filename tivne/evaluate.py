"""Evaluate a finished (or interrupted) run against its sequence and merge the result into metrics.json.

    python -m tivne.evaluate run_dir=PATH [mesh.times=[t1,t2]] [mesh.resolution=0.02] [frame=first_camera|ate]
                             [settings.window_s=0.5] [settings.threshold_m=0.05] ...

The dataset and the render settings are rebuilt from the run's own config (run_dir/.hydra/config.yaml);
see :mod:`tivne.evaluation` for what is measured. A run without trajectory.txt is refused (its
metrics.json keeps what it has). Mesh times outside the run's recorded range are
refused before anything is written. The new metrics are printed as JSON. Errors are one
``error: ...`` line, exit status 2.
"""

from __future__ import annotations

import json
import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from data_modules.errors import overrides_checked
from tivne.cli import check_known_keys, mesh_settings, one_line_errors, quote_run_dir, register_defaults, run_sequence
from tivne.config import MeshEvalSettings
from tivne.evaluation import evaluate_run
from tivne.slam.outputs import RunDir

register_defaults()


@overrides_checked
@hydra.main(config_path="../conf", config_name="evaluate", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> None:
    check_known_keys(cfg, ("run_dir", "frame", "prefer_mesh_files", "mesh", "settings"))
    mesh = mesh_settings(cfg.mesh)
    settings = MeshEvalSettings.from_mapping(OmegaConf.to_container(cfg.settings, resolve=True))
    run = RunDir(cfg.run_dir)
    view, render = run_sequence(run.root)
    if not run.trajectory.is_file():  # evaluating it would replace the ATE metrics.json holds by nulls
        raise FileNotFoundError(f"{run.trajectory}: not found; the run has no poses to evaluate (resume=true continues an interrupted run)")
    run.check_writable()  # before the work, not after: metrics.json will be written there
    metrics = evaluate_run(run.root, view, mesh, settings, render, cfg.frame, bool(cfg.prefer_mesh_files))
    run.merge_metrics(metrics)
    if metrics.get("ate_partial"):
        print(f"warning: partial run: ATE over {metrics.get('ate_frames')} of {metrics['sequence_frames']} frames", file=sys.stderr)
    print(json.dumps(metrics, indent=2, sort_keys=True))


if __name__ == "__main__":
    sys.argv = quote_run_dir(sys.argv)  # a sweep job dir as printed (tivne.cli.quote_run_dir)
    main()
