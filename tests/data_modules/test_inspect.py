"""`python -m data_modules.inspect`: the summary, GT export, contact sheet and error handling."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.inspect import (
    contact_sheet,
    gt_trajectory,
    run,
    sample_indices,
    summarize,
)
from data_modules.sequence import SequenceDataset, SequenceView
from data_modules.tables import read_tum_trajectory

REPO = Path(__file__).resolve().parents[2]
SMALL = ["dataset.width=80", "dataset.height=60", "dataset.num_frames=5", "dataset.cache_dir=null"]
sys.path.insert(0, str(REPO / "tests"))
from cli_worker import run_commands  # noqa: E402


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


@pytest.fixture(scope="module")
def cli(tmp_path_factory) -> tuple[Path, dict[str, subprocess.CompletedProcess]]:
    """The two command lines of the CLI tests below, run once in one worker process
    (tests/cli_worker.py) in one empty folder; the refusal, whose stderr is checked whole, first: it
    starts with nothing imported, as a new process does."""
    cwd = tmp_path_factory.mktemp("inspect_cli")
    env = {**os.environ, "TIVNE_CACHE_DIR": str(cwd / "cache"), "OMP_NUM_THREADS": "1"}
    commands = {"bad input": [*SMALL, "data.stride=0"], "text": [*SMALL, "gt_out=gt.txt", "sheet_out=sheet.png", "sheet_frames=3"]}
    results = run_commands([("data_modules.inspect", args) for args in commands.values()], cwd=cwd, env=env)
    return cwd, dict(zip(commands, results))


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


def test_cli_text_gt_and_sheet(cli):
    tmp_path, outs = cli
    res = outs["text"]
    assert res.returncode == 0, res.stderr
    assert "frames:       5" in res.stdout and "80 x 60" in res.stdout and "sampled 5 of 5" in res.stdout
    ts, poses = read_tum_trajectory(tmp_path / "gt.txt")
    from data_modules.synthetic import SyntheticSequence as MovingCubeSequence

    ds = MovingCubeSequence(num_frames=5, width=80, height=60)
    assert np.allclose(ts, ds.timestamps, atol=1e-6)
    assert torch.allclose(poses, ds.camera_poses(), atol=1e-6)
    sheet = cv2.imread(str(tmp_path / "sheet.png"))
    assert sheet.shape == (3 * 60, 3 * 80, 3)
    # No Hydra output folders or logs, no cache (cache_dir=null): from either command.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.txt", "sheet.png"]


def test_cli_bad_input_one_line_exit_2(cli):
    res = cli[1]["bad input"]
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


# ------------------------------------------------------------------------- warnings and OpenCV noise


def _fixtures():
    sys.path.insert(0, str(Path(__file__).parent))
    import fixtures

    return fixtures


def _run_capturing(capsys, *overrides: str) -> tuple[int, list[str], str]:
    status = _fixtures().run_inspect_inprocess(*overrides, "format=json")
    out = capsys.readouterr()
    return status, out.err.splitlines(), out.out


def test_reader_warnings_are_shown_one_line_each(tmp_path, capsys):
    fx = _fixtures()
    # KLG whose header frame count is short (an unfinished recording)
    fx.make_klg(tmp_path / "t.klg", header_count=0)
    small = [f"dataset.width={fx.W}", f"dataset.height={fx.H}", "dataset.fx=20", "dataset.fy=20", "dataset.cx=16", "dataset.cy=12"]
    status, err, out = _run_capturing(capsys, "dataset=teddy", f"dataset.root={tmp_path / 't.klg'}", *small)
    assert status == 0 and json.loads(out)["frames"] == 3
    assert err == [f"warning: {tmp_path / 't.klg'}: header says 0 frames, found 3 (unfinished recording?); using all"]
    # TUM: the 4th colour image has no depth within 0.02 s
    fx.make_tum(tmp_path / "tum", n=4)
    status, err, out = _run_capturing(capsys, "dataset=tum", f"dataset.root={tmp_path / 'tum'}")
    assert status == 0 and json.loads(out)["frames"] == 3
    assert err == [f"warning: {tmp_path / 'tum'}: 1 colour images without depth within 0.020 s skipped"]
    # Co-Fusion without calibration.txt: the configured fallback intrinsics are used
    fx.make_cofusion(tmp_path / "cf", calib=None)
    fallback = [f"dataset.fallback_intrinsics.{k}={v}" for k, v in dict(fx=10, fy=10, cx=16, cy=12, width=fx.W, height=fx.H).items()]
    status, err, out = _run_capturing(capsys, "dataset=room4", f"dataset.root={tmp_path / 'cf'}", *fallback)
    assert status == 0 and json.loads(out)["frames"] == 3
    assert err == [f"warning: {tmp_path / 'cf'}: calibration.txt missing, using the configured fallback intrinsics"]
    # the data_modules loggers are back as they were
    assert logging.getLogger("data_modules").propagate and not logging.getLogger("data_modules").handlers


def test_warnings_then_one_line_error(tmp_path, capsys):
    fx = _fixtures()
    fx.make_klg(tmp_path / "t.klg", header_count=0)
    status, err, out = _run_capturing(capsys, "dataset=teddy", f"dataset.root={tmp_path / 't.klg'}", "data.stride=0", "dataset.width=32",
                                      "dataset.height=24", "dataset.cx=16", "dataset.cy=12")
    assert status == 2 and out == ""
    assert err == [f"warning: {tmp_path / 't.klg'}: header says 0 frames, found 3 (unfinished recording?); using all",
                   "error: data.stride: must be >= 1, got 0"]


def test_python_warnings_become_one_line(capsys):
    import warnings

    from data_modules.inspect import reader_warnings_on_stderr

    with reader_warnings_on_stderr():
        warnings.warn("cache: cannot write the frame cache\nsecond line")
    assert capsys.readouterr().err == "warning: cache: cannot write the frame cache\n"


def test_corrupt_image_gives_one_line_without_opencv_warnings(tmp_path, capfd):
    # OpenCV writes its "[ WARN:0@...]" lines straight to file descriptor 2: capture at fd level
    fx = _fixtures()
    fx.make_folder(tmp_path / "rec", n=2, masks=False)
    depth = tmp_path / "rec" / "depth" / "1.png"
    depth.write_bytes(depth.read_bytes()[:60])  # a PNG cut inside its first chunk
    status = fx.run_inspect_inprocess("dataset=folder", f"dataset.root={tmp_path / 'rec'}", "format=json")
    err = capfd.readouterr().err.splitlines()
    assert status == 2
    assert err == [f"error: {depth}: cannot decode image (not a valid PNG/JPEG file?)"]


def test_colour_camera_estimate_in_the_summary(capsys):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("inspect", overrides=["dataset.width=160", "dataset.height=120", "dataset.num_frames=8", "dataset.cache_dir=null",
                                            "colour_camera=true", "max_sampled=8"])
    assert run(cfg) == 0
    out = capsys.readouterr().out
    assert "colour camera: [" in out and "dataset.colour_camera=[" in out
    cam = [float(v) for v in out.split("dataset.colour_camera=[")[1].split("]")[0].split(",")]
    assert len(cam) == 4 and all(v > 0 for v in cam)  # the cube's colour is registered: about its depth camera
    assert abs(cam[0] / 128.0 - 1) < 0.1 and abs(cam[2] - 79.5) < 16
