"""The provider contract (base): none, dataset, the recording wrapper, and every masks config."""

from __future__ import annotations

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
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(CONF / "masks" / f"{name}.yaml")
    target = cfg.provider._target_
    module, cls = target.rsplit(".", 1)
    import importlib

    assert hasattr(importlib.import_module(module), cls)


def test_recording_wrapper_keeps_masks():
    rec = RecordingMasks(DatasetMasks())
    gt = square(1, 1, 4)
    assert torch.equal(rec(make_frame(3, mask=gt), None), gt)
    assert torch.equal(rec.masks[3], gt) and torch.equal(rec.gt[3], gt) and rec.timestamps[3] == 3 / 30.0
    assert not hasattr(RecordingMasks, "instances")  # no global registry: callers keep their object
