"""What a command reads besides its checked sections, checked before anything is built: no unknown
top-level key (``+resmue=true`` is an error, not ignored), the dataset node naming one of TivNe's
readers with checked arguments, an allowed mask provider, and ``data.*`` (:mod:`tivne.readers`)."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

from omegaconf import DictConfig, OmegaConf

from tivne.config import SECTIONS, ConfigError, default_tree
from tivne.readers import DataConfig, check_dataset_node, check_masks_node

RUN_KEYS = ("paths", "data", "dataset", "masks", "seed", "hydra")


def check_known_keys(cfg: DictConfig, known: Iterable[str]) -> None:
    """Refuse a top-level key the command does not know (``+resmue=true`` is an error, not ignored)."""
    known = {*known, "hydra"}
    unknown = sorted(set(cfg) - known)
    if unknown:
        close = difflib.get_close_matches(unknown[0], sorted(known), n=1)
        hint = f"did you mean {close[0]}? " if close else ""
        raise ConfigError(f"{unknown[0]}: unknown setting ({hint}known top-level keys: {', '.join(sorted(known - {'hydra'}))})")


def check_stream_inputs(cfg: DictConfig) -> DataConfig:
    """The dataset node (one of TivNe's readers, checked arguments), the mask provider (an allowed
    one) and ``data.*``, checked before anything is instantiated; returns ``data.*``."""
    check_dataset_node(OmegaConf.to_container(cfg.dataset, resolve=True, throw_on_missing=False))
    provider = OmegaConf.select(cfg, "masks.provider")
    if provider is not None:
        check_masks_node(OmegaConf.to_container(provider, resolve=True, throw_on_missing=False))
    return DataConfig.from_mapping(OmegaConf.to_container(cfg.data, resolve=True))


def check_run_inputs(cfg: DictConfig) -> DataConfig:
    """What ``tivne.train`` reads besides its sections: no unknown top-level key, then
    :func:`check_stream_inputs`."""
    check_known_keys(cfg, (*default_tree(SECTIONS), *RUN_KEYS))
    return check_stream_inputs(cfg)


