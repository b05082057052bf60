"""Entry point: ``python -m tivne.train dataset=cube field=tivne sampler=mask_weighted keyframe=overlap``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import hydra
import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from data_modules.frame import DatasetError
from data_modules.sequence import SequenceDataModule
from tivne.field.networks import TimeVaryingField
from tivne.keyframes import KeyframePolicy
from tivne.losses import LossWeights
from tivne.mapping import MappingConfig
from tivne.rendering import RenderConfig
from tivne.runtime import configure_runtime
from tivne.sampling import PixelSampler
from tivne.system import OutputConfig, TivNeSLAM, write_metrics
from tivne.tracking import TrackingConfig


def plain(node: Any) -> dict[str, Any]:
    return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]


def build_system(cfg: DictConfig, intrinsics, run_dir: str | Path) -> TivNeSLAM:
    """Compose the typed stages from the Hydra config (the only place that reads it)."""
    field_kwargs = plain(cfg.field)
    field_kwargs.pop("name", None)
    output = plain(cfg.output)
    output["mesh_times"] = tuple(output.get("mesh_times") or ())
    return TivNeSLAM(
        field=TimeVaryingField(**field_kwargs),
        field_kwargs=field_kwargs,
        intrinsics=intrinsics,
        sampler=PixelSampler(**plain(cfg.sampler)),
        keyframes=KeyframePolicy(**plain(cfg.keyframe)),
        masks=instantiate(cfg.masks.provider),
        render=RenderConfig(**plain(cfg.render)),
        loss=LossWeights(**plain(cfg.loss)),
        tracking=TrackingConfig(**plain(cfg.tracking)),
        mapping=MappingConfig(**plain(cfg.mapping)),
        output=OutputConfig(**output),
        run_dir=run_dir,
        seed=int(cfg.seed),
    )


def run(cfg: DictConfig, run_dir: str | Path) -> dict[str, Any]:
    """Run SLAM over the configured sequence and return metrics.json's content."""
    configure_runtime(cfg.runtime.threads, cfg.runtime.tune_allocator)
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    dataset = instantiate(cfg.dataset)
    datamodule = SequenceDataModule(dataset, **plain(cfg.data))
    system = build_system(cfg, datamodule.intrinsics, run_dir)
    trainer = L.Trainer(
        max_epochs=1,
        accelerator=cfg.trainer.accelerator,
        devices=cfg.trainer.devices,
        logger=TensorBoardLogger(save_dir=str(run_dir), name="", version="tb", default_hp_metric=False),
        enable_checkpointing=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        inference_mode=False,
        log_every_n_steps=1,
        enable_progress_bar=bool(cfg.trainer.progress_bar),
        default_root_dir=str(run_dir),
    )
    trainer.fit(system, datamodule=datamodule)
    metrics = dict(system.last_metrics)
    if cfg.output.evaluate:
        try:
            from tivne.evaluate import evaluate_run
        except ImportError:
            evaluate_run = None
        if evaluate_run is not None:
            extra = evaluate_run(Path(run_dir), dataset_view=datamodule.view, mesh_resolution=cfg.output.mesh_resolution)
            write_metrics(Path(run_dir) / "metrics.json", extra)
            metrics.update(extra)
    return metrics


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    run_dir = HydraConfig.get().runtime.output_dir
    try:
        metrics = run(cfg, run_dir)
    except (DatasetError, MissingMandatoryValue) as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except Exception as exc:  # a reader's DatasetError wrapped by Hydra's instantiate
        cause = exc.__cause__ or exc.__context__
        if isinstance(cause, (DatasetError, MissingMandatoryValue)):
            print(f"error: {cause}", file=sys.stderr)
            sys.exit(2)
        raise
    keys = ["frames", "s_per_frame", "track_ms_per_iter", "map_ms_per_iter", "ate_rmse_m", "peak_rss_mb"]
    print(json.dumps({k: metrics.get(k) for k in keys}))
    print(f"results in {run_dir}")
    return metrics.get("ate_rmse_m")  # the value a sweeper would minimise


if __name__ == "__main__":
    main()
