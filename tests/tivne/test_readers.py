"""tivne.readers: only TivNe's own readers and mask providers, every argument checked, before any instantiate."""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import pytest
from hydra.utils import get_class
from omegaconf import OmegaConf

from tivne.readers import MASK_PROVIDERS, READERS, DataConfig, check_dataset_node, check_masks_node, targets_in
from tivne.settings import ConfigError

CONF = Path(__file__).resolve().parents[2] / "conf"


def preset(path: Path) -> dict:
    cfg = OmegaConf.merge({"paths": {"cache_dir": None}}, {"dataset": OmegaConf.load(path)})
    return OmegaConf.to_container(cfg.dataset, resolve=True, throw_on_missing=False)


@pytest.mark.parametrize("path", sorted((CONF / "dataset").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_dataset_preset_is_an_allowed_reader_with_valid_arguments(path):
    node = preset(path)
    assert node["_target_"] in READERS
    check_dataset_node(node)  # the shipped defaults pass their own checks


@pytest.mark.parametrize("target", sorted(READERS))
def test_reader_settings_are_arguments_of_the_reader(target):
    cls = get_class(target)
    params = set(inspect.signature(cls.__init__).parameters) - {"self", "kwargs"}
    if "kwargs" in inspect.signature(cls.__init__).parameters:  # Bonn: marker_to_camera + TUM's
        params |= set(inspect.signature(cls.__mro__[1].__init__).parameters) - {"self", "kwargs"}
    fields = {f.name for f in dataclasses.fields(READERS[target])}
    assert fields <= params, fields - params


@pytest.mark.parametrize("path", sorted((CONF / "masks").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_mask_preset_is_an_allowed_provider(path):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=[f"masks={path.stem}"])
    node = OmegaConf.to_container(cfg.masks.provider, throw_on_missing=False)
    assert check_masks_node(node) in MASK_PROVIDERS


def test_the_two_provider_allowlists_agree():
    """The run-folder check (tivne.readers, below the masks layer) and the settings registry
    (tivne.masks.settings) name the same providers."""
    from tivne.masks.settings import PROVIDERS

    assert set(PROVIDERS) == set(MASK_PROVIDERS)


@pytest.mark.parametrize("node, message", [
    ({"_target_": "builtins.open", "_args_": ["x", "w"]}, r"dataset._target_='builtins.open': not one of TivNe's own"),
    ({"_target_": "os.system", "command": "true"}, r"dataset._target_='os.system'"),
    ({"root": "x"}, r"dataset: must be a config node with a _target_"),
    ({"_target_": "data_modules.folder.FolderSequence", "root": "x", "intrinsics": {"_target_": "builtins.eval"}},
     r"dataset.intrinsics._target_='builtins.eval'"),
    ({"_target_": "data_modules.folder.FolderSequence", "root": "x", "intrinsics": {"fx": {"_target_": "data_modules.folder.FolderSequence"}}},
     r"dataset.intrinsics.fx._target_"),  # an allowed target is still refused below the top
    ({"_target_": "data_modules.folder.FolderSequence", "_args_": ["x"]}, r"dataset._args_: not allowed"),
    ({"_target_": "data_modules.tum.TUMSequence", "root": "x", "max_time_diff": -1}, r"dataset.max_time_diff=-1.0: must be >= 0"),
    ({"_target_": "data_modules.tum.TUMSequence", "root": "x", "depth_scale": float("nan")}, r"dataset.depth_scale=nan: must be a finite"),
    ({"_target_": "data_modules.tum.TUMSequence", "root": "x", "speed": 2}, r"dataset.speed: unknown setting"),
    ({"_target_": "data_modules.klg.KLGSequence", "root": "x", "width": 1.5}, r"dataset.width=1.5: must be an integer"),
    ({"_target_": "data_modules.tum.TUMSequence", "root": "x", "readout_s": -0.03}, r"dataset.readout_s=-0.03: must be >= 0 and < 1"),
    ({"_target_": "data_modules.tum.BonnSequence", "root": "x", "readout_s": 2}, r"dataset.readout_s=2.0: must be >= 0 and < 1"),
    ({"_target_": "data_modules.cofusion.CoFusionSequence", "root": "x", "original_is_ray_distance": 1}, r"original_is_ray_distance=1"),
    ({"_target_": "data_modules.synthetic.SyntheticSequence", "sensor": {"axial": "big"}}, r"dataset.sensor.axial='big': must be a finite number"),
    ({"_target_": "data_modules.folder.FolderSequence", "root": "x", "intrinsics": {"fx": 1, "fz": 2}}, r"dataset.intrinsics.fz: unknown"),
])
def test_bad_dataset_nodes_are_one_line_errors(node, message):
    with pytest.raises(ConfigError, match=message):
        check_dataset_node(node)


def test_mask_providers_are_checked_at_every_depth():
    assert check_masks_node({"_target_": "tivne.masks.base.NoMasks"}) == "tivne.masks.base.NoMasks"
    with pytest.raises(ConfigError, match=r"masks.provider._target_='subprocess.Popen'"):
        check_masks_node({"_target_": "subprocess.Popen", "args": ["true"]})
    with pytest.raises(ConfigError, match=r"masks.provider.weights._target_"):
        check_masks_node({"_target_": "tivne.masks.maskrcnn.MaskRCNNMasks", "weights": {"_target_": "builtins.open"}})
    assert [k for k, _ in targets_in({"a": [{"_target_": 1}], "_target_": 2}, "n")] == ["n.a[0]._target_", "n._target_"]


@pytest.mark.parametrize("values, message", [
    ({"stride": 1.5}, r"data.stride=1.5: must be an integer >= 1"),
    ({"stride": 0}, r"data.stride=0: must be >= 1"),
    ({"max_frames": 0}, r"data.max_frames=0"),
    ({"resize": [640]}, r"data.resize=\[640\]: must be \[width, height\]"),
    ({"resize": [640, 0]}, r"data.resize"),
    ({"depth_max": float("nan")}, r"data.depth_max=nan: must be a finite number"),
    ({"depth_min": 2.0, "depth_max": 1.0}, r"data.depth_max=1.0: must be > data.depth_min"),
    ({"strides": 2}, r"data.strides: unknown setting"),
])
def test_data_settings_are_checked(values, message):
    with pytest.raises(ConfigError, match=message):
        DataConfig.from_mapping(values)


def test_data_defaults_match_the_yaml():
    yaml = OmegaConf.to_container(OmegaConf.load(CONF / "data" / "default.yaml"))
    assert DataConfig.from_mapping(yaml).view_kwargs() == DataConfig().view_kwargs() | {"depth_max": yaml["depth_max"]}
