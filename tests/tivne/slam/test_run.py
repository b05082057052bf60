"""The run's settings as the app layer resolves them from the composed config."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from data_modules.sensor import KINECT_COLOUR_BASELINE_M
from tivne.slam.run import TrainSettings

CONF = Path(__file__).resolve().parents[3] / "conf"
UNREGISTERED = ["dataset=tum", "dataset.root=some/folder", "dataset.camera=custom", "dataset.fx=585", "dataset.fy=585", "dataset.cx=320",
                "dataset.cy=240", "dataset.colour_camera=[527,531,315,238]"]


@pytest.mark.parametrize(
    "overrides, expected",
    [
        ([], 0.0),  # the synthetic cube: registered colour
        (["dataset=tum", "dataset.root=some/folder"], 0.0),  # TUM: registered by the driver
        (UNREGISTERED, KINECT_COLOUR_BASELINE_M),  # remapped by a colour camera alone: the baseline is left out
        (UNREGISTERED + ["dataset.colour_offset=[0.025,0.0]"], 0.0),  # the offset modelled
        (UNREGISTERED + ["odometry.colour_parallax_m=0.01"], 0.01),  # the user's value wins
    ],
)
def test_colour_parallax_follows_how_the_dataset_registers_colour(overrides, expected):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    assert TrainSettings.from_config(cfg).odometry.colour_parallax_m == pytest.approx(expected)


@pytest.mark.parametrize("dataset, readout_s", [("tum", 0.03), ("bonn", 0.03), ("teddy", 0.03), ("cube", None)])
def test_the_camera_trackers_rolling_shutter_is_the_datasets(dataset, readout_s):
    """The real readers' presets read rows over 30 ms (Kinect v1, Xtion); the loop's tracker takes the
    readout from the dataset's intrinsics (the synthetic family renders a global shutter)."""
    from data_modules.frame import Intrinsics
    from tivne.slam.run import build_loop

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=[f"dataset={dataset}", "dataset.root=some/folder"] if readout_s else [])
    assert cfg.dataset.get("readout_s") == readout_s
    camera = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480, readout_s=readout_s or 0.0)
    assert build_loop(TrainSettings.from_config(cfg), camera).tracker.readout_s == (readout_s or 0.0)
