"""The library entry of a training run (what ``python -m tivne.train``, the benchmarks and the tests
call): the checked settings of a composed config, the loop built from them, and :func:`run`, which
drives it over the configured sequence with a Lightning Trainer and writes the run directory.

The run directory: one that already holds results is refused unless ``resume=true`` (continue an
interrupted run from ``checkpoints/slam.pt``: same overrides, same folder; the frames it processed
are skipped) or ``overwrite=true`` (its results are cleared first); see
:func:`tivne.slam.outputs.check_run_dir`.
"""

from __future__ import annotations

import sys
import typing
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from data_modules.frame import Intrinsics
from data_modules.sensor import KINECT_COLOUR_BASELINE_M
from data_modules.sequence import SequenceDataModule
from tivne.config import (
    AllocationConfig,
    BackendConfig,
    ConfigError,
    FieldConfig,
    FieldTrackingConfig,
    KeyframeConfig,
    LossWeights,
    MappingConfig,
    MeshConfig,
    ObjectFieldConfig,
    ObjectiveConfig,
    ObjectsConfig,
    OdometryConfig,
    OutputConfig,
    RenderConfig,
    RunDirConfig,
    RuntimeConfig,
    SamplerConfig,
    TrackingConfig,
    TrainerConfig,
    ViewerConfig,
)
from tivne.evaluation import evaluate_run
from tivne.field.objects import attach_optimizer, build_field
from tivne.field.oracle import attach_tracks
from tivne.inputs import check_run_inputs
from tivne.limits import check_run_size
from tivne.masks.base import MaskProvider
from tivne.masks.settings import build_provider, check_provider
from tivne.meshing import select_mesh_times
from tivne.render.samplers import PixelSampler
from tivne.runlock import run_lock
from tivne.slam.allocation import VoxelAllocator
from tivne.slam.backend import make_backend
from tivne.slam.checkpoint import load_resume_state, set_global_rng_state
from tivne.slam.keyframes import KeyframePolicy, KeyframeStore
from tivne.slam.loop import SlamLoop
from tivne.slam.mapping import Mapper
from tivne.slam.objects import ObjectTracker
from tivne.slam.observer import RunObserver
from tivne.slam.outputs import RunDir, check_run_dir, tensorboard_hparams
from tivne.slam.results import RunWriter
from tivne.slam.system import TivNeSLAM, restore
from tivne.slam.tracking import Tracker
from tivne.utils import InterruptSignalsFirst, RunFailed, RunInterrupted, configure_runtime, interrupt_signals, require_device
from tivne.viewer import make_observer, progress_callbacks


def plain(node: Any) -> dict[str, Any]:
    return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]


@dataclass(frozen=True)
class TrainSettings:
    """Every checked section of a training run's config."""

    runtime: RuntimeConfig
    field: FieldConfig
    object_field: ObjectFieldConfig
    render: RenderConfig
    loss: LossWeights
    tracking: TrackingConfig
    field_tracking: FieldTrackingConfig
    odometry: OdometryConfig
    mapping: MappingConfig
    keyframe: KeyframeConfig
    sampler: SamplerConfig
    mesh: MeshConfig
    output: OutputConfig
    allocation: AllocationConfig
    trainer: TrainerConfig
    objective: ObjectiveConfig
    objects: ObjectsConfig
    viewer: ViewerConfig
    backend: BackendConfig

    @classmethod
    def from_config(cls, cfg: DictConfig) -> "TrainSettings":
        """Check every section (raises :class:`tivne.config.ConfigError` naming the bad key)."""
        sections = typing.get_type_hints(cls)
        settings = cls(**{name: kind.from_mapping(plain(cfg[name])) for name, kind in sections.items()})
        if settings.odometry.colour_parallax_m is None:  # null: from how the dataset registers colour
            settings = replace(settings, odometry=replace(settings.odometry, colour_parallax_m=unmodelled_parallax(cfg.get("dataset"))))
        if settings.field.name == "objects" and settings.object_field.tracks == "tracked" and not settings.objects.track:
            raise ConfigError("object_field.tracks=tracked: the object fields are placed by the object tracker; set objects.track=true "
                              "(or object_field.tracks=oracle for the dataset's GT object poses)")
        return settings


def unmodelled_parallax(dataset: DictConfig | None) -> float:
    """``odometry.colour_parallax_m`` for ``null`` (:class:`tivne.config.OdometryConfig`): the Kinect's
    RGB–IR baseline where a dataset section remaps colour by ``colour_camera`` alone, else 0."""
    remapped = dataset is not None and dataset.get("colour_camera") is not None and dataset.get("colour_offset") is None
    return KINECT_COLOUR_BASELINE_M if remapped else 0.0


def build_loop(settings: TrainSettings, intrinsics: Intrinsics, masks: MaskProvider | None = None, seed: int = 0) -> SlamLoop:
    """The SLAM loop with every component built from its checked section."""
    s = settings
    field = build_field(s.field, s.object_field)
    # The next frames' tracking reads the first frame's map unless it is pure odometry: then it gets
    # all its steps at once (mapping.first_now defers them only where nothing waits on them).
    mapping = replace(s.mapping, first_now=s.mapping.first_iters) if s.tracking.reads_map else s.mapping
    mapper = Mapper(field, mapping, PixelSampler(s.sampler), s.render, s.loss)
    attach_optimizer(field, mapper.optimizer, s.mapping)  # field=objects: object fields join the map optimiser
    loop = SlamLoop(
        field=field,
        intrinsics=intrinsics,
        tracker=Tracker(s.tracking, s.field_tracking, s.odometry, s.render, s.loss, readout_s=intrinsics.readout_s),
        mapper=mapper,
        keyframes=KeyframeStore(s.keyframe),
        policy=KeyframePolicy(s.keyframe),
        allocator=VoxelAllocator(s.allocation),
        masks=masks,
        seed=seed,
        objects=ObjectTracker(s.objects, intrinsics.K(), s.odometry, masks=getattr(masks, "name", "none")) if s.objects.track else None,
        backend=make_backend(s.backend, s.odometry, intrinsics.readout_s),
    )
    if loop.objects is not None and s.object_field.tracks == "tracked":  # field=objects placed by the tracker's live poses
        attach_tracks(field, None, s.object_field, lambda: loop.object_tracks)
    return loop


def loop_from_config(cfg: DictConfig, intrinsics: Intrinsics, masks: MaskProvider | None = None) -> SlamLoop:
    """The loop a composed config describes, its mask provider included (``masks`` replaces it)."""
    provider = masks if masks is not None else build_provider(plain(cfg.masks.provider))
    return build_loop(TrainSettings.from_config(cfg), intrinsics, provider, int(cfg.seed))


def build_system(
    cfg: DictConfig, intrinsics: Intrinsics, run_dir: str | Path, settings: TrainSettings | None = None, masks: MaskProvider | None = None,
    observer: RunObserver | None = None,
) -> TivNeSLAM:
    """The LightningModule around a loop composed from ``cfg``; ``masks`` (a provider object)
    replaces ``cfg.masks.provider``; ``observer`` watches the run (a viewer)."""
    s = settings or TrainSettings.from_config(cfg)
    provider = masks if masks is not None else build_provider(plain(cfg.masks.provider))
    loop = build_loop(s, intrinsics, provider, int(cfg.seed))
    writer = RunWriter(run_dir, s.output, s.mesh, run_config(cfg), observer)
    return TivNeSLAM(loop, writer, s.output.image_every)


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
    :class:`tivne.masks.base.RecordingMasks` around the configured one). One run at a time
    writes into ``run_dir`` (:mod:`tivne.runlock`).
    """
    with run_lock(run_dir):
        return run_locked(cfg, run_dir, masks)


def run_locked(cfg: DictConfig, run_dir: str | Path, masks: MaskProvider | None = None) -> dict[str, Any]:
    """:func:`run` once the run folder's lock is held."""
    settings = TrainSettings.from_config(cfg)  # before any data is read
    data = check_run_inputs(cfg)  # known keys, TivNe's own reader and mask provider, data.*
    if masks is None:
        check_provider(plain(cfg.masks.provider))
    options = run_dir_options(cfg)
    device = require_device(settings.trainer.accelerator)
    check_run_dir(RunDir(run_dir), options.resume, options.overwrite)  # results there are refused, nothing is changed yet
    runtime = configure_runtime(settings.runtime.threads, settings.runtime.tune_allocator)
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    dataset = instantiate(cfg.dataset)
    datamodule = SequenceDataModule(dataset, **data.view_kwargs())
    size = datamodule.intrinsics
    check_run_size(size.width, size.height, len(datamodule.view), settings.keyframe.every, settings.keyframe.max_stored,
                   settings.field.max_capacity, settings.field.embed_dim)  # before the first frame: tivne.limits
    select_mesh_times(datamodule.view.timestamps, list(settings.mesh.times) or None)  # refuse bad times before the run
    resume = prepare_run_dir(cfg, options, run_dir, datamodule.view.timestamps)
    viewer = make_observer(settings.viewer, run_dir, datamodule.intrinsics, settings.output.image_every)  # viewer=rerun
    system = build_system(cfg, datamodule.intrinsics, run_dir, settings, masks, observer=viewer)
    if settings.object_field.tracks == "oracle":  # field=objects on the GT object poses (the ablation's upper bound)
        attach_tracks(system.field, datamodule.view, settings.object_field)
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
        enable_progress_bar=settings.trainer.progress_bar and sys.stdout.isatty(),  # plain lines elsewhere
        default_root_dir=str(run_dir),
        # TivNe's SIGINT / SIGTERM handlers over Lightning's; one plain progress line every N frames off a terminal
        callbacks=[InterruptSignalsFirst(), *progress_callbacks(settings.trainer, sys.stdout.isatty())],
    )
    try:
        with interrupt_signals():
            if datamodule.start < len(datamodule.view):
                trainer.fit(system, datamodule=datamodule)
            else:  # every frame was processed before the crash: the final pass and the results are left
                system.to(device)
                set_global_rng_state(restore(system.loop, system.resume_payload))
                system.writer.finish(system.loop, logger.experiment)
            extra = {"threads": runtime["threads"]}
            if settings.output.evaluate:
                extra |= evaluate_run(Path(run_dir), datamodule.view, settings.mesh, render=settings.render)
            metrics = RunDir(run_dir).merge_metrics(extra)
    except RunInterrupted as exc:
        if not system.writer.last_metrics.get("complete"):  # a second signal now is the default action: exit at once
            system.writer.save_partial(system.loop, f"interrupted by {exc} after {len(system.loop)} frames")
        raise
    finally:
        getattr(viewer, "close", lambda: None)()  # the recording file is whole, whatever happened
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
