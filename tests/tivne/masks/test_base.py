"""The provider contract (base): none, dataset, the recording wrapper, and every masks config."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest
import torch

from tivne.masks.base import DatasetMasks, NoMasks, RecordingMasks
from tivne.masks.geometric import GeometricMasks

sys.path.insert(0, str(Path(__file__).parent))
from mask_scenes import CONF, make_frame, square  # noqa: E402


def test_none_and_dataset_providers():
    gt = square(5, 5, 10)
    frame = make_frame(mask=gt)
    assert NoMasks()(frame, None) is None
    assert torch.equal(DatasetMasks()(frame, None), gt)
    assert DatasetMasks()(make_frame(), None) is None
    assert not NoMasks.needs_tracked_pose and GeometricMasks.needs_tracked_pose


@pytest.mark.parametrize("name", ["dataset", "none", "folder", "maskrcnn", "geometric"])
def test_every_mask_config_names_a_provider(name):
    import importlib

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from tivne.masks.settings import PROVIDERS

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=[f"masks={name}"])
    node = OmegaConf.to_container(cfg.masks.provider)
    target = node.pop("_target_")
    assert PROVIDERS[target][0] == name
    settings = PROVIDERS[target][1]
    assert set(node) == {f.name for f in dataclasses.fields(settings)}  # every setting, from its one default
    module, cls = target.rsplit(".", 1)
    assert hasattr(importlib.import_module(module), cls)


def test_recording_wrapper_keeps_masks():
    rec = RecordingMasks(DatasetMasks())
    gt = square(1, 1, 4)
    assert torch.equal(rec(make_frame(3, mask=gt), None), gt)
    assert torch.equal(rec.masks[3], gt) and torch.equal(rec.gt[3], gt) and rec.timestamps[3] == 3 / 30.0
    assert not hasattr(RecordingMasks, "instances")  # no global registry: callers keep their object
