"""Entry point: ``python -m tivne.train dataset=cube field=tivne sampler=mask_weighted keyframe=overlap``.

The only place that reads the Hydra config: it checks every section against :mod:`tivne.config`
before any data is read, composes the typed stages and hands them to the Lightning trainer. It
returns the ``objective`` (:mod:`tivne.evaluation.objective`), the value a sweeper minimises
(``-m hydra/sweeper=optuna``, see ``conf/experiment/search_tracking.yaml``).

The run directory (``hydra.run.dir``): one that already holds results is refused unless
``resume=true`` (continue an interrupted run from ``checkpoints/slam.pt``: same overrides, same
folder; the frames it processed are skipped) or ``overwrite=true`` (its results are cleared first);
see :func:`tivne.slam.outputs.check_run_dir`. On the command line the check runs before Hydra
writes anything into the folder (:class:`tivne.cli.RunDirGuard`).
"""

from __future__ import annotations

import json
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from data_modules.sequence import SequenceDataModule
from tivne.cli import in_multirun, one_line_errors, register_defaults
from tivne.config import (
    FieldConfig,
    KeyframeConfig,
    LossWeights,
    MappingConfig,
    MeshConfig,
    ObjectFieldConfig,
    ObjectiveConfig,
    OdometryConfig,
    OutputConfig,
    RenderConfig,
    RunDirConfig,
    RuntimeConfig,
    SamplerConfig,
    TrackingConfig,
    TrainerConfig,
)
from tivne.evaluation import evaluate_run
from tivne.evaluation.objective import objective_value
from tivne.field.oracle import attach_oracle
from tivne.masks.base import MaskProvider
from tivne.meshing import select_mesh_times
from tivne.render.samplers import PixelSampler
from tivne.slam.checkpoint import load_resume_state
from tivne.slam.keyframes import KeyframePolicy
from tivne.slam.outputs import RunDir, check_run_dir, tensorboard_hparams
from tivne.slam.system import TivNeSLAM
from tivne.utils import RunFailed, RunInterrupted, configure_runtime, interrupt_signals, require_device

register_defaults()


def plain(node: Any) -> dict[str, Any]:
    return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]


@dataclass(frozen=True)
class TrainSettings:
    """Every checked section of a training run's config."""

    runtime: RuntimeConfig
    field: FieldConfig
    objects: ObjectFieldConfig
    render: RenderConfig
    loss: LossWeights
    tracking: TrackingConfig
    odometry: OdometryConfig
    mapping: MappingConfig
    keyframe: KeyframeConfig
    sampler: SamplerConfig
    mesh: MeshConfig
    output: OutputConfig
    trainer: TrainerConfig
    objective: ObjectiveConfig

    @classmethod
    def from_config(cls, cfg: DictConfig) -> "TrainSettings":
        """Check every section (raises :class:`tivne.config.ConfigError` naming the bad key)."""
        sections = typing.get_type_hints(cls)
        return cls(**{name: kind.from_mapping(plain(cfg[name])) for name, kind in sections.items()})


def build_system(
    cfg: DictConfig, intrinsics, run_dir: str | Path, settings: TrainSettings | None = None, masks: MaskProvider | None = None
) -> TivNeSLAM:
    """Compose the typed stages from the config; ``masks`` (a provider object) replaces ``cfg.masks.provider``."""
    s = settings or TrainSettings.from_config(cfg)
    return TivNeSLAM(
        field_cfg=s.field,
        intrinsics=intrinsics,
        sampler=PixelSampler(s.sampler),
        keyframes=KeyframePolicy(s.keyframe),
        masks=masks if masks is not None else instantiate(cfg.masks.provider),
        render=s.render,
        loss=s.loss,
        tracking=s.tracking,
        odometry=s.odometry,
        mapping=s.mapping,
        mesh=s.mesh,
        output=s.output,
        run_dir=run_dir,
        seed=int(cfg.seed),
        run_config=run_config(cfg),
        objects=s.objects,
    )


def run_config(cfg: DictConfig) -> dict[str, Any]:
    """The composed config as plain values, without Hydra's own node: what a resumed run must repeat."""
    values = plain(cfg)
    values.pop("hydra", None)
    return values


def run_dir_options(cfg: DictConfig) -> RunDirConfig:
    """The checked top-level ``resume`` / ``overwrite`` keys."""
    return RunDirConfig.from_mapping({key: cfg.get(key, False) for key in ("resume", "overwrite")})


def prepare_run_dir(cfg: DictConfig, options: RunDirConfig, run_dir: str | Path, timestamps) -> dict[str, Any] | None:
    """Once the run is sure to start: clear the folder for overwrite, or for resume return the
    checkpoint to continue from (checked against this config and the sequence's ``timestamps``)."""
    run = RunDir(run_dir)
    if options.resume:
        return load_resume_state(run.checkpoint, run_config(cfg), timestamps)
    if options.overwrite:
        run.clear_results()
    return None


def run(cfg: DictConfig, run_dir: str | Path, masks: MaskProvider | None = None) -> dict[str, Any]:
    """Run SLAM over the configured sequence and return metrics.json's content.

    ``masks``: a provider object to use instead of ``cfg.masks.provider`` (e.g. a benchmark's
    :class:`tivne.masks.base.RecordingMasks` around the configured one).
    """
    settings = TrainSettings.from_config(cfg)  # before any data is read
    options = run_dir_options(cfg)
    device = require_device(settings.trainer.accelerator)
    check_run_dir(RunDir(run_dir), options.resume, options.overwrite)  # results there are refused, nothing is changed yet
    runtime = configure_runtime(settings.runtime.threads, settings.runtime.tune_allocator)
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    dataset = instantiate(cfg.dataset)
    datamodule = SequenceDataModule(dataset, **plain(cfg.data))
    select_mesh_times(datamodule.view.timestamps, list(settings.mesh.times) or None)  # refuse bad times before the run
    resume = prepare_run_dir(cfg, options, run_dir, datamodule.view.timestamps)
    system = build_system(cfg, datamodule.intrinsics, run_dir, settings, masks)
    attach_oracle(system.field, datamodule.view, settings.objects)  # field=objects: GT object poses until tracking lands
    if resume is not None:
        datamodule.start = system.resume_from(resume)
    logger = TensorBoardLogger(save_dir=str(run_dir), name="", version=RunDir.TENSORBOARD, default_hp_metric=False)
    trainer = L.Trainer(
        max_epochs=1,
        accelerator=settings.trainer.accelerator,
        devices=settings.trainer.devices,
        logger=logger,
        enable_checkpointing=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        inference_mode=False,
        log_every_n_steps=1,
        enable_progress_bar=settings.trainer.progress_bar,
        default_root_dir=str(run_dir),
    )
    try:
        with interrupt_signals():
            if datamodule.start < len(datamodule.view):
                trainer.fit(system, datamodule=datamodule)
            else:  # every frame was processed before the crash: the final pass and the results are left
                system.to(device)
                system.on_train_start()
                system.on_train_end()
            extra = {"threads": runtime["threads"]}
            if settings.output.evaluate:
                extra |= evaluate_run(Path(run_dir), datamodule.view, settings.mesh, render=settings.render)
            metrics = RunDir(run_dir).merge_metrics(extra)
    except RunInterrupted as exc:
        if not system.last_metrics.get("complete"):  # a second signal now is the default action: exit at once
            system.save_partial(f"interrupted by {exc} after {len(system.trajectory)} frames")
        raise
    tensorboard_hparams(logger, plain(cfg), metrics)
    check_tracked(run_dir, metrics)
    return metrics


def check_tracked(run_dir: str | Path, metrics: dict[str, Any]) -> None:
    """Refuse a run where most frames have no tracked pose (their poses are guesses; a trajectory of
    them must not pass for a result): metrics.json gets the reason as ``error``, then RunFailed."""
    frames = int(metrics.get("frames") or 0)
    untracked = int(metrics.get("tracking_lost") or 0) + int(metrics.get("frames_without_tracking") or 0)
    if frames > 1 and untracked > (frames - 1) / 2:
        reason = (
            f"{untracked} of {frames - 1} frames could not be tracked ({metrics.get('frames_without_tracking')} without usable "
            f"static depth, {metrics.get('tracking_lost')} lost); see the warnings above and metrics.json"
        )
        RunDir(run_dir).merge_metrics({"error": reason})
        raise RunFailed(reason)


# An absolute path: the same whether this module runs as __main__ or as tivne.train (below).
CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> float | None:
    run_dir = HydraConfig.get().runtime.output_dir
    try:
        metrics = run(cfg, run_dir)
    except RunInterrupted as exc:
        print(f"interrupted by {exc}: partial results (complete: false) in {run_dir}", file=sys.stderr)
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
