"""Co-Fusion synthetic folder reader on tiny self-written sequences."""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from fixtures import H, W, make_cofusion, write_exr, write_png_rgb  # noqa: E402

from data_modules.cofusion import CoFusionSequence, ray_distance_factor  # noqa: E402
from data_modules.frame import DatasetError  # noqa: E402


def _check_round_trip(ds, truth):
    assert len(ds) == len(truth.numbers)
    for i in range(len(ds)):
        f = ds[i]
        np.testing.assert_array_equal(np.round(f.rgb.numpy() * 255).astype(np.uint8), truth.rgb[i])
        np.testing.assert_array_equal(f.depth.numpy(), truth.depth[i])
        assert f.depth.dtype == torch.float32
        if truth.mask_ids:
            np.testing.assert_array_equal(f.mask.numpy(), truth.mask_ids[i] != 0)
            np.testing.assert_array_equal(f.instances.numpy(), truth.mask_ids[i])
        np.testing.assert_allclose(f.gt_pose.numpy(), truth.poses[i], atol=1e-9)
        assert f.source == f"Color{truth.numbers[i]:04d}.png"


@pytest.mark.parametrize("exr,half", [("Y", False), ("Y", True), ("RGB", False), ("RGB", True)])
def test_round_trip(tmp_path, exr, half):
    truth = make_cofusion(tmp_path / "room4-full", exr=exr, half=half)
    ds = CoFusionSequence(tmp_path / "room4-full")
    assert ds.name == "room4-full"
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (20, 21, 15.5, 11.5, W, H)
    assert ds.has_masks and ds.has_gt_poses and ds.gt_valid.all()
    np.testing.assert_allclose(ds.timestamps, np.array([1, 2, 3]) / 24.0)
    _check_round_trip(ds, truth)


def test_object_trajectories_and_fps(tmp_path):
    truth = make_cofusion(tmp_path / "seq", n=4, first=5)
    ds = CoFusionSequence(tmp_path / "seq", fps=30.0)
    np.testing.assert_allclose(ds.timestamps, np.arange(5, 9) / 30.0)
    assert ds.frame_numbers.tolist() == [5, 6, 7, 8]
    assert list(ds.object_trajectories) == ["car-2"] and ds.object_ids == {"car-2": 2}
    frames, poses = ds.object_trajectories["car-2"]
    assert frames.tolist() == [6, 7, 8]
    np.testing.assert_allclose(poses.numpy(), np.stack(truth.object_poses), atol=1e-9)
    assert ds.describe()["objects"] == ["car-2"]


def test_calibration_four_numbers_and_masks_id_three_channels(tmp_path):
    truth = make_cofusion(tmp_path / "s", calib="20 21 15.5 11.5", masks="masks_id", mask_channels=3)
    ds = CoFusionSequence(tmp_path / "s")
    assert (ds.intrinsics.width, ds.intrinsics.height) == (W, H)
    _check_round_trip(ds, truth)
    assert CoFusionSequence(tmp_path / "s", masks=False)[0].mask is None


def test_timestamps_file(tmp_path):
    make_cofusion(tmp_path / "s")
    (tmp_path / "s" / "times.txt").write_text("# t\n0.5\n0.6\n0.75\n")
    ds = CoFusionSequence(tmp_path / "s", timestamps_file="times.txt")
    np.testing.assert_allclose(ds.timestamps, [0.5, 0.6, 0.75])
    assert ds[2].timestamp == 0.75
    (tmp_path / "s" / "times.txt").write_text("0.5\n0.4\n0.75\n")
    with pytest.raises(DatasetError, match=r"times\.txt: timestamps are not strictly increasing at entry 1"):
        CoFusionSequence(tmp_path / "s", timestamps_file="times.txt")
    (tmp_path / "s" / "times.txt").write_text("0.5\n0.6\n")
    with pytest.raises(DatasetError, match=r"times\.txt: has 2 timestamps but the sequence has 3 frames"):
        CoFusionSequence(tmp_path / "s", timestamps_file="times.txt")


def test_gt_partial_coverage(tmp_path):
    make_cofusion(tmp_path / "s")
    gt = tmp_path / "s" / "trajectories" / "gt-cam-0.txt"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:1] + lines[2:]) + "\n")  # drop frame 1
    ds = CoFusionSequence(tmp_path / "s")
    assert ds.gt_valid.tolist() == [False, True, True]
    assert ds[0].gt_pose is None and ds[1].gt_pose is not None


def test_blender_axes_switch(tmp_path):
    truth = make_cofusion(tmp_path / "s")
    ds = CoFusionSequence(tmp_path / "s", blender_camera_axes=True)
    np.testing.assert_allclose(ds[0].gt_pose.numpy(), truth.poses[0] @ np.diag([1, -1, -1, 1]), atol=1e-9)


def test_depth_original_ray_distance_auto(tmp_path):
    root = tmp_path / "s"
    truth = make_cofusion(root, calib="5 5 15.5 11.5 32 24")  # short focal length: big ray factors
    ds0 = CoFusionSequence(root)
    factor = ray_distance_factor(ds0.intrinsics)
    for num, d in zip(truth.numbers, truth.depth):
        write_exr(root / "depth_original" / f"Depth{num:04d}.exr", {"R": d * factor, "G": d * factor, "B": d * factor})
    ds = CoFusionSequence(root, depth="original")
    assert ds.ray_distance
    np.testing.assert_allclose(ds[1].depth.numpy(), truth.depth[1], rtol=1e-6)
    # z-depth original is detected as such
    for num, d in zip(truth.numbers, truth.depth):
        write_exr(root / "depth_original" / f"Depth{num:04d}.exr", {"R": d, "G": d, "B": d})
    ds = CoFusionSequence(root, depth="original")
    assert not ds.ray_distance
    np.testing.assert_array_equal(ds[1].depth.numpy(), truth.depth[1])
    assert not CoFusionSequence(root, depth="original", original_is_ray_distance=False).ray_distance


def test_fallback_intrinsics(tmp_path):
    make_cofusion(tmp_path / "s", calib=None)
    with pytest.raises(DatasetError, match=r"calibration\.txt: calibration file not found"):
        CoFusionSequence(tmp_path / "s")
    ds = CoFusionSequence(tmp_path / "s", fallback_intrinsics={"fx": 10, "fy": 10, "cx": 16, "cy": 12})
    assert (ds.intrinsics.fx, ds.intrinsics.width) == (10, W)


# ----------------------------------------------------------------------------------- bad input


def test_principal_point_outside_the_image(tmp_path):
    make_cofusion(tmp_path / "s", calib="20 21 15.5 5000 32 24")
    with pytest.raises(DatasetError, match=r"calibration\.txt: principal point \(cx=15\.5, cy=5000\) is outside the 32x24 image"):
        CoFusionSequence(tmp_path / "s")
    make_cofusion(tmp_path / "t", calib=None)
    with pytest.raises(DatasetError, match=r"^dataset\.fallback_intrinsics: principal point \(cx=320, cy=240\) is outside the 32x24"):
        CoFusionSequence(tmp_path / "t", fallback_intrinsics={"fx": 10, "fy": 10, "cx": 320, "cy": 240})


def test_missing_root(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: Co-Fusion sequence folder not found"):
        CoFusionSequence(tmp_path / "nowhere")


def test_missing_subfolder(tmp_path):
    make_cofusion(tmp_path / "s")
    shutil.rmtree(tmp_path / "s" / "depth_noise")
    with pytest.raises(DatasetError, match=r"depth_noise: depth_noise folder not found"):
        CoFusionSequence(tmp_path / "s")
    with pytest.raises(DatasetError, match=r"depth_original: depth_original folder not found"):
        CoFusionSequence(tmp_path / "s", depth="original")


def test_missing_frame_in_middle(tmp_path):
    make_cofusion(tmp_path / "s", n=4)
    (tmp_path / "s" / "colour" / "Color0002.png").unlink()
    with pytest.raises(DatasetError, match=r"Color0002\.png: missing \(frames 1\.\.4 expected without gaps\)"):
        CoFusionSequence(tmp_path / "s")


def test_missing_depth_and_mask(tmp_path):
    make_cofusion(tmp_path / "s")
    (tmp_path / "s" / "mask_id" / "Mask0003.png").unlink()
    with pytest.raises(DatasetError, match=r"Mask0003\.png: missing \(colour frame Color0003\.png exists\)"):
        CoFusionSequence(tmp_path / "s")
    (tmp_path / "s" / "depth_noise" / "Depth0002.exr").unlink()
    with pytest.raises(DatasetError, match=r"Depth0002\.exr: missing"):
        CoFusionSequence(tmp_path / "s")


def test_exr_without_usable_channel(tmp_path):
    make_cofusion(tmp_path / "s")
    d = np.ones((H, W), np.float32)
    write_exr(tmp_path / "s" / "depth_noise" / "Depth0002.exr", {"A": d, "foo": d})
    ds = CoFusionSequence(tmp_path / "s")
    ds[0]
    with pytest.raises(DatasetError, match=r"Depth0002\.exr: no usable depth channel"):
        ds[1]


def test_unreadable_png(tmp_path):
    make_cofusion(tmp_path / "s")
    (tmp_path / "s" / "colour" / "Color0003.png").write_bytes(b"\x89PNG\r\n broken")
    with pytest.raises(DatasetError, match=r"Color0003\.png: cannot decode image"):
        CoFusionSequence(tmp_path / "s")[2]


def test_rgb_depth_size_mismatch(tmp_path):
    make_cofusion(tmp_path / "s")
    write_png_rgb(tmp_path / "s" / "colour" / "Color0002.png", np.zeros((H + 2, W, 3), np.uint8))
    with pytest.raises(DatasetError, match=rf"Depth0002\.exr: depth is {W}x{H} but colour Color0002\.png is {W}x{H + 2}"):
        CoFusionSequence(tmp_path / "s")[1]


def test_depth_size_differs_from_calibration(tmp_path):
    make_cofusion(tmp_path / "s", calib="20 21 15.5 11.5 64 48")
    with pytest.raises(DatasetError, match=rf"Depth0001\.exr: depth is {W}x{H} but the sequence is 64x48"):
        CoFusionSequence(tmp_path / "s")[0]


def test_calibration_too_few_numbers(tmp_path):
    make_cofusion(tmp_path / "s", calib="360 360 320")
    with pytest.raises(DatasetError, match=r"calibration\.txt:1: expected 4 to 6 fields"):
        CoFusionSequence(tmp_path / "s")


def test_trajectory_malformed(tmp_path):
    make_cofusion(tmp_path / "s")
    gt = tmp_path / "s" / "trajectories" / "gt-cam-0.txt"
    lines = gt.read_text().splitlines()
    lines[2] = "2 0.1 0.2 oops 0 0 0 1"
    gt.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"gt-cam-0\.txt:3: bad tz 'oops'"):
        CoFusionSequence(tmp_path / "s")
    obj = tmp_path / "s" / "trajectories" / "gt-car-2.txt"
    make_cofusion(tmp_path / "t")
    (tmp_path / "t" / "trajectories" / "gt-car-2.txt").write_text("2 1 2 3\n")
    with pytest.raises(DatasetError, match=r"gt-car-2\.txt:1: expected 8 fields"):
        CoFusionSequence(tmp_path / "t")
    assert obj.exists()


def test_bad_options(tmp_path):
    make_cofusion(tmp_path / "s")
    with pytest.raises(DatasetError, match="dataset.depth"):
        CoFusionSequence(tmp_path / "s", depth="clean")
    with pytest.raises(DatasetError, match="dataset.fps"):
        CoFusionSequence(tmp_path / "s", fps=0)


# --------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize("config", ["room4", "toycar3"])
def test_config_instantiates(tmp_path, config):
    from fixtures import instantiate_dataset

    truth = make_cofusion(tmp_path / "seq")
    ds = instantiate_dataset(config, tmp_path / "seq")
    assert isinstance(ds, CoFusionSequence) and ds.name == config
    _check_round_trip(ds, truth)
    with pytest.raises(DatasetError, match=r"wrong: Co-Fusion sequence folder not found"):
        instantiate_dataset(config, tmp_path / "wrong")


def test_config_root_is_mandatory():
    from fixtures import CONF_DIR
    from omegaconf import OmegaConf

    for name in ("room4", "toycar3", "teddy", "tum", "bonn", "folder"):
        cfg = OmegaConf.load(CONF_DIR / f"{name}.yaml")
        assert OmegaConf.is_missing(cfg, "root"), name
        assert cfg._target_.startswith("data_modules.")


# --------------------------------------------------------------------------- data_modules.inspect


def test_inspect_summarize(tmp_path):
    from data_modules.inspect import summarize

    make_cofusion(tmp_path / "s", n=3)
    s = summarize(CoFusionSequence(tmp_path / "s"))
    assert (s["frames"], s["width"], s["height"]) == (3, W, H)
    assert s["has_gt_poses"] and s["has_masks"]
    assert s["valid_depth_pct"] == pytest.approx(100 * (1 - 1 / (W * H)))  # one absurd pixel per frame
    assert s["dynamic_pct"] == pytest.approx(100 * 60 / (W * H))
    assert s["duration_s"] == pytest.approx(2 / 24) and s["fps"] == pytest.approx(24)
    assert s["depth_min_m"] == 0.5 and s["depth_max_m"] <= 39 / 8


def test_inspect_json_and_gt_out(tmp_path, capsys):
    """The inspect command's body on a toycar3 sequence, in this process as the other readers' tests
    run it (a new interpreter spends ~9 s importing Lightning; the command line itself, its exit
    status and its files, is tested in test_inspect.py)."""
    import json

    from fixtures import run_inspect_inprocess

    from data_modules.tables import read_tum_trajectory

    truth = make_cofusion(tmp_path / "car4-full", n=3)
    gt = tmp_path / "gt.txt"
    assert run_inspect_inprocess("dataset=toycar3", f"dataset.root={tmp_path / 'car4-full'}", "format=json", f"gt_out={gt}") == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (s["name"], s["frames"], s["width"], s["height"]) == ("toycar3", 3, W, H)
    assert s["has_gt_poses"] and s["has_masks"]
    assert s["valid_depth_pct"] == pytest.approx(100 * (1 - 1 / (W * H)))
    ts, poses = read_tum_trajectory(gt)
    np.testing.assert_allclose(ts, np.array([1, 2, 3]) / 24, atol=1e-6)
    np.testing.assert_allclose(poses.numpy(), np.stack(truth.poses), atol=1e-6)


def test_inspect_wrong_root_one_line(tmp_path, capsys):
    from fixtures import run_inspect_inprocess

    assert run_inspect_inprocess("dataset=room4", f"dataset.root={tmp_path / 'nowhere'}", "format=json") == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [f"error: {tmp_path / 'nowhere'}: Co-Fusion sequence folder not found"]
