"""A finished run as a rerun recording: ``python -m tivne.view run_dir=PATH [every=10]``.

Writes run_dir/view.rrd (:func:`tivne.viewer.offline.record_run`: cameras and trajectory against
GT, per-frame error, GT object boxes, the 4D mesh sequence on the time slider), or with
``viewer.sink=spawn|serve`` streams it to a viewer; open the file with ``rerun run_dir/view.rrd``.
The sequence (GT, frames) comes from the run's own run_dir/.hydra/config.yaml; without it the
recording has the run's own parts only, with a warning. Needs ``pip install -e '.[viewer]'``.
Errors are one ``error: ...`` line, exit status 2.
"""

from __future__ import annotations

import sys

import hydra
import torch
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from data_modules.frame import DatasetError
from tivne.cli import error_line, mesh_settings, one_line_errors, quote_run_dir, register_defaults, run_sequence
from tivne.config import ConfigError, MeshConfig, ViewerConfig, default_tree
from tivne.slam.outputs import RunDir
from tivne.utils import require_device
from tivne.viewer.offline import record_run

register_defaults()
ConfigStore.instance().store(name="tivne_view", node=default_tree((MeshConfig, ViewerConfig)))  # conf/view.yaml's defaults


@hydra.main(config_path="../conf", config_name="view", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> None:
    viewer = ViewerConfig.from_mapping(OmegaConf.to_container(cfg.viewer, resolve=True))
    if viewer.kind != "rerun":
        raise ConfigError("viewer.kind: tivne.view writes a rerun recording; leave it at rerun")
    mesh = mesh_settings(cfg.mesh)
    device = require_device(cfg.device) if cfg.device else ("cuda" if torch.cuda.is_available() else "cpu")
    run = RunDir(cfg.run_dir)
    if not run.root.is_dir():
        raise FileNotFoundError(f"{run.root}: run directory not found")
    view = None
    try:
        view, _ = run_sequence(run.root)
    except (DatasetError, FileNotFoundError) as exc:  # the recording still shows what the run saved
        print(f"warning: no ground truth or frames in the recording ({error_line(exc).removeprefix('error: ')})", file=sys.stderr)
    summary = record_run(run.root, view, cfg.every, mesh, viewer, cfg.out, device, cfg.until)
    if summary.gt_reason:
        print(f"warning: no ground truth in the recording: {summary.gt_reason}", file=sys.stderr)
    print(f"frames={summary.frames} meshes={len(summary.meshes)} error_frames={summary.error_frames} path={summary.path}")


if __name__ == "__main__":
    sys.argv = quote_run_dir(sys.argv)
    main()
