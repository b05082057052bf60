"""The mask preprocessing CLI (tivne.make_masks): writes, resumes, round-trips through FolderMasks."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent / "masks"))
from mask_scenes import CONF, H, W, make_frame, square  # noqa: E402

from data_modules.frame import DatasetError, Frame, Intrinsics  # noqa: E402
from tivne.make_masks import make_masks  # noqa: E402
from tivne.masks.base import DatasetMasks  # noqa: E402
from tivne.masks.folder import FolderMasks  # noqa: E402
from tivne.masks.geometric import GeometricMasks  # noqa: E402


class TinyView:
    intrinsics = Intrinsics(50.0, 50.0, W / 2, H / 2, W, H)

    def __init__(self, n: int = 4) -> None:
        self.frames = [make_frame(10 + i, mask=square(2 + i, 3 + i, 6)) for i in range(n)]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]


class CountingProvider(DatasetMasks):
    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, frame, context):
        self.calls += 1
        return super().__call__(frame, context)


def test_make_masks_writes_resumes_and_round_trips(tmp_path):
    view = TinyView()
    provider = CountingProvider()
    counts = make_masks(provider, view, tmp_path, progress=False)
    assert counts == {"written": 4, "skipped": 0, "empty": 0}
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["000010.png", "000011.png", "000012.png", "000013.png"]
    assert not list(tmp_path.glob(".*tmp"))
    (tmp_path / "000012.png").write_bytes(b"half-written")  # an interrupted write
    (tmp_path / "000013.png").unlink()
    counts = make_masks(provider, view, tmp_path, progress=False)
    assert counts == {"written": 2, "skipped": 2, "empty": 0} and provider.calls == 6
    folder = FolderMasks(root=str(tmp_path))
    for f in view.frames:
        assert torch.equal(folder(f, None), f.mask)


def test_make_masks_refuses_pose_providers(tmp_path):
    with pytest.raises(DatasetError, match="needs the tracked pose"):
        make_masks(GeometricMasks(), TinyView(), tmp_path, progress=False)


def compose_make_masks(overrides):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="make_masks", overrides=overrides)


def test_make_masks_cli_needs_out():
    from omegaconf.errors import MissingMandatoryValue

    from tivne import make_masks as cli

    with pytest.raises(MissingMandatoryValue):
        cli.run(compose_make_masks(["masks=none", "dataset.num_frames=2"]))


def test_make_masks_cli_writes_a_folder(tmp_path):
    from tivne import make_masks as cli

    out = tmp_path / "masks"
    cfg = compose_make_masks([
        "masks=dataset", "dataset.num_frames=3", "dataset.width=32", "dataset.height=24",
        "dataset.cache_dir=null", f"out={out}", "progress=false",
    ])
    assert cli.run(cfg)["written"] == 3
    assert sorted(p.name for p in out.glob("*.png")) == ["000000.png", "000001.png", "000002.png"]
