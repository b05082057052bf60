"""Evaluate a finished run against ground truth and merge the result into its metrics.json.

    python -m tivne.evaluate run_dir=PATH [mesh.resolution=0.02] [mesh.times=[t1,t2]] [frame=first_camera|ate]

The dataset is rebuilt from the run's own config (run_dir/.hydra/config.yaml); see
:mod:`tivne.evaluation` for what is measured. The merged metrics are printed as JSON. Errors are one
``error: ...`` line, exit status 2.
"""

from __future__ import annotations

import json

import hydra
from omegaconf import DictConfig, OmegaConf

from tivne.cli import mesh_settings, one_line_errors, register_defaults
from tivne.config import MeshEvalSettings
from tivne.evaluation import evaluate_run
from tivne.slam.outputs import RunDir

register_defaults()


@hydra.main(config_path="../conf", config_name="evaluate", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> None:
    mesh = mesh_settings(cfg.mesh)
    settings = MeshEvalSettings.from_mapping(OmegaConf.to_container(cfg.settings, resolve=True))
    run = RunDir(cfg.run_dir)
    metrics = evaluate_run(
        run.root,
        mesh_resolution=mesh.resolution,
        times=list(mesh.times) or None,
        frame=cfg.frame,
        settings=settings,
        prefer_mesh_files=bool(cfg.prefer_mesh_files),
        mesh_culling=mesh,
    )
    run.merge_metrics(metrics)
    print(json.dumps(metrics, indent=2, sort_keys=True))


if __name__ == "__main__":
    main()
