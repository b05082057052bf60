"""backend.method=graph inside the per-frame loop: keyframes become graph nodes, the counters reach
metrics.json, and a run restored from its checkpoint continues with the same graph."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from tivne.slam.checkpoint import read_checkpoint
from tivne.slam.results import run_metrics
from tivne.slam.run import build_system

pytest.importorskip("gtsam")

CONF = Path(__file__).resolve().parents[4] / "conf"


def smoke_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=["experiment=smoke", "dataset.cache_dir=null", *overrides])


def feed(system, frames, start: int) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # self.log without a Trainer
        for k, frame in enumerate(frames, start):
            system.training_step(frame, k)
        system.flush()  # the module runs one frame behind the stream: the segment's last frame too


def test_resume_restores_the_graph_in_the_loop(tmp_path, tiny_cube):
    cfg = smoke_cfg("backend.method=graph", "keyframe.every=2", "output.save_every=0", "output.checkpoint_every=3")
    frames = [tiny_cube[k] for k in range(6)]
    whole = build_system(cfg, tiny_cube.intrinsics, tmp_path / "whole")
    feed(whole, frames[:3], 0)
    shutil.copy(tmp_path / "whole" / "checkpoints" / "slam.pt", tmp_path / "at3.pt")
    feed(whole, frames[3:], 3)
    graph = whole.loop.backend
    assert graph.counters.keyframes == 3 and graph.counters.edges >= 2
    assert list(graph.graph.nodes) == whole.loop.keyframes.frame_ids()
    metrics = run_metrics(whole.loop)
    assert metrics["graph_edges"] == graph.counters.edges and "graph_optimise_ms" in metrics
    assert metrics["graph_closures"] == [list(c) for c in graph.closures]

    resumed = build_system(cfg, tiny_cube.intrinsics, tmp_path / "resumed")
    resumed.resume_from(read_checkpoint(tmp_path / "at3.pt"))
    resumed.on_train_start()
    assert list(resumed.loop.backend.graph.nodes) == [0, 2]
    feed(resumed, frames[3:], 3)
    timings = ("optimise_ms", "align_ms")
    counts = lambda s: {k: v for k, v in vars(s.loop.backend.counters).items() if k not in timings}  # noqa: E731
    assert counts(resumed) == counts(whole)
    torch.testing.assert_close(resumed.loop.poses.all(), whole.loop.poses.all(), atol=1e-5, rtol=0)
