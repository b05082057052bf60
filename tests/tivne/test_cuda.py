"""The same code on CUDA (skipped without a CUDA device; bench/gpu_check.sh runs these where one is)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from tivne.slam.checkpoint import load_checkpoint
from tivne.slam.run import run

CONF = Path(__file__).resolve().parents[2] / "conf"
pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.parametrize("tracking", ["odometry", "field"])
def test_a_smoke_run_on_cuda_tracks_maps_and_meshes(tmp_path, tracking):
    overrides = ["experiment=smoke", "dataset.width=80", "dataset.height=60", "dataset.cache_dir=null", "trainer=gpu",
                 f"tracking={tracking}", "output.evaluate=true"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    metrics = run(cfg, tmp_path)
    assert metrics["frames"] == 5 and math.isfinite(metrics["ate_rmse_m"]) and metrics["ate_rmse_m"] < 0.05
    assert metrics["mesh_t0.133_faces"] > 0
    field, _ = load_checkpoint(tmp_path / "checkpoints" / "slam.pt", device="cuda")
    assert field.grid.embeddings.is_cuda
