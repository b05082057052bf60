"""`python -m data_modules.inspect`: the summary, GT export, contact sheet and error handling."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.inspect import contact_sheet, gt_trajectory, run, sample_indices, summarize
from data_modules.sequence import SequenceDataset, SequenceView
from tivne.geometry import read_tum_trajectory

REPO = Path(__file__).resolve().parents[2]
SMALL = ["dataset.width=80", "dataset.height=60", "dataset.num_frames=5", "dataset.cache_dir=null"]


class _NoGT(SequenceDataset):
    """Three 16x12 frames without masks or GT poses; frame 1 has half its depth invalid."""

    name = "nogt"

    def __init__(self) -> None:
        self.intrinsics = Intrinsics(10.0, 10.0, 7.5, 5.5, 16, 12)
        self.timestamps = np.array([1.0, 1.5, 2.0])

    def load_frame(self, i: int) -> Frame:
        depth = torch.full((12, 16), 2.0 + i)
        if i == 1:
            depth[:, :8] = 0
        return Frame(i, float(self.timestamps[i]), torch.zeros(12, 16, 3), depth)


def _cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "TIVNE_CACHE_DIR": str(cwd / "cache"), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "data_modules.inspect", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )


def test_sample_indices():
    assert list(sample_indices(5, 20)) == [0, 1, 2, 3, 4]
    assert list(sample_indices(101, 3)) == [0, 50, 100]
    assert len(sample_indices(0, 3)) == 0


def test_summarize_cube(tiny_cube):
    view = SequenceView(tiny_cube, max_frames=4)
    s = summarize(view)
    frames = [view[i] for i in range(4)]
    depth = torch.stack([f.depth for f in frames])
    assert s["name"] == "cube" and s["frames"] == 4 and s["frames_sampled"] == 4
    assert s["duration_s"] == pytest.approx(0.1) and s["fps"] == pytest.approx(30.0)
    assert (s["width"], s["height"], s["fx"], s["fy"], s["cx"], s["cy"]) == (80, 60, 64.0, 64.0, 39.5, 29.5)
    assert s["depth_min_m"] == pytest.approx(float(depth.min())) and s["depth_max_m"] == pytest.approx(float(depth.max()))
    assert 0.5 < s["depth_min_m"] < s["depth_max_m"] < 4.0
    assert s["valid_depth_pct"] == pytest.approx(100.0)  # noise-free
    dyn = 100 * float(torch.stack([f.mask for f in frames]).float().mean())
    assert s["dynamic_pct"] == pytest.approx(dyn) and 1 < dyn < 40
    assert s["has_gt_poses"] is True and s["has_masks"] is True
    assert summarize(view, max_sampled=2)["frames_sampled"] == 2
    json.dumps(s)  # plain JSON types only


def test_summarize_without_masks_and_gt():
    s = summarize(SequenceView(_NoGT()))
    assert s["dynamic_pct"] is None and s["has_masks"] is False and s["has_gt_poses"] is False
    assert s["valid_depth_pct"] == pytest.approx(100 * (3 * 192 - 96) / (3 * 192))
    assert (s["depth_min_m"], s["depth_max_m"]) == (2.0, 4.0)
    with pytest.raises(DatasetError, match="no ground-truth"):
        gt_trajectory(SequenceView(_NoGT()))
    sheet = contact_sheet(SequenceView(_NoGT()), rows=2)
    assert sheet.shape == (24, 48, 3) and sheet.dtype == np.uint8


def test_gt_trajectory_uses_camera_pose(tiny_cube):
    ts, poses = gt_trajectory(SequenceView(tiny_cube, stride=2))
    assert np.allclose(ts, [0.0, 2 / 30, 4 / 30])
    assert torch.equal(poses[1], tiny_cube.camera_pose(2))


def test_run_json_in_process(capsys):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("inspect", overrides=[*SMALL, "format=json", "data.max_frames=3"])
    assert run(cfg) == 0
    out = capsys.readouterr().out
    s = json.loads(out)
    assert out.count("\n") == 1 and s["frames"] == 3 and s["width"] == 80 and s["has_masks"] is True
    for key in ("duration_s", "fx", "fy", "cx", "cy", "depth_min_m", "depth_max_m", "valid_depth_pct", "dynamic_pct", "frames_sampled"):
        assert key in s


def test_cli_text_gt_and_sheet(tmp_path):
    res = _cli([*SMALL, "gt_out=gt.txt", "sheet_out=sheet.png", "sheet_frames=3"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert "frames:       5" in res.stdout and "80 x 60" in res.stdout and "sampled 5 of 5" in res.stdout
    ts, poses = read_tum_trajectory(tmp_path / "gt.txt")
    from data_modules.synthetic import SyntheticSequence as MovingCubeSequence

    ds = MovingCubeSequence(num_frames=5, width=80, height=60)
    assert np.allclose(ts, ds.timestamps, atol=1e-6)
    assert torch.allclose(poses, ds.camera_poses(), atol=1e-6)
    sheet = cv2.imread(str(tmp_path / "sheet.png"))
    assert sheet.shape == (3 * 60, 3 * 80, 3)
    # No Hydra output folders or logs, no cache (cache_dir=null).
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.txt", "sheet.png"]


def test_cli_bad_input_one_line_exit_2(tmp_path):
    res = _cli([*SMALL, "data.stride=0"], tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip() == "error: data.stride: must be >= 1, got 0"
    assert res.stdout == ""


@pytest.mark.parametrize(
    "override, message",
    [
        ("dataset.width=8", "error: dataset.width: must be an integer >= 16 pixels, got 8"),
        ("dataset.num_frames=???", "error: missing mandatory config value 'dataset.num_frames'"),
        ("format=yaml", "error: format: must be 'text' or 'json', got 'yaml'"),
    ],
)
def test_run_errors_in_process(capsys, override, message):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("inspect", overrides=[*SMALL, override])
    assert run(cfg) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith(message) and captured.err.count("\n") == 1
