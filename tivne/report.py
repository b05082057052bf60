"""A run's report: ``python -m tivne.report run_dir=PATH [report.frames=4] [report.mesh_width=480]``.

Writes run_dir/report.html and its PNGs in run_dir/report/ (:mod:`tivne.reporting.page`; figures are
drawn with matplotlib's Agg canvas, no display needed) and prints their paths as JSON. The sequence (ground truth, observed frames) is rebuilt from the run's own
run_dir/.hydra/config.yaml; when it cannot be (a dataset that is not on this machine) the report is
written without those parts, with a warning. Errors are one ``error: ...`` line, exit status 2.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from data_modules.errors import overrides_checked
from data_modules.frame import DatasetError
from tivne.cli import check_known_keys, error_line, one_line_errors, quote_run_dir, register_defaults, run_sequence
from tivne.config import RenderConfig, ReportConfig
from tivne.reporting.page import report_summary, write_report
from tivne.slam.outputs import RunDir

register_defaults()


@overrides_checked
@hydra.main(config_path="../conf", config_name="report", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> None:
    check_known_keys(cfg, ("run_dir", "report"))
    settings = ReportConfig.from_mapping(OmegaConf.to_container(cfg.report, resolve=True))
    run = RunDir(cfg.run_dir)
    if not run.root.is_dir():
        raise FileNotFoundError(f"{run.root}: run directory not found")
    view, render = None, RenderConfig()
    try:
        view, render = run_sequence(run.root)
    except (DatasetError, FileNotFoundError) as exc:  # the report still shows what the run saved
        print(f"warning: no ground truth or observed frames in the report ({error_line(exc).removeprefix('error: ')})", file=sys.stderr)
    page, images = write_report(run.root, view, render, settings)
    print(report_summary(page, images))


if __name__ == "__main__":
    sys.argv = quote_run_dir(sys.argv)  # a sweep job dir as printed (tivne.cli.quote_run_dir)
    main()
