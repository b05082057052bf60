"""The generic folder layout reader on tiny self-written sequences."""

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from fixtures import H, W, make_folder, random_pose, write_png8, write_png_rgb  # noqa: E402

from data_modules.folder import FolderSequence  # noqa: E402
from data_modules.frame import DatasetError  # noqa: E402


def test_round_trip_fps_and_natural_order(tmp_path):
    truth = make_folder(tmp_path / "rec", n=12)
    ds = FolderSequence(tmp_path / "rec", fps=10.0)
    assert ds.name == "rec" and len(ds) == 12 and ds.timestamp_source == "fps"
    assert [p.stem for p in ds.rgb_paths] == [str(k) for k in range(12)]  # 2 before 10
    np.testing.assert_allclose(ds.timestamps, np.arange(12) / 10.0)
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (20, 21, 15.5, 11.5, W, H)
    assert ds.has_masks and not ds.has_gt_poses
    for i in (0, 2, 11):
        f = ds[i]
        np.testing.assert_array_equal(np.round(f.rgb.numpy() * 255).astype(np.uint8), truth.rgb[i])
        np.testing.assert_allclose(f.depth.numpy(), truth.depth[i], rtol=1e-7)
        np.testing.assert_array_equal(f.mask.numpy(), truth.masks[i])
        assert f.gt_pose is None and f.source == f"{i}.png"


def test_timestamp_names_and_poses(tmp_path):
    rng = np.random.default_rng(0)
    P = [random_pose(rng) for _ in range(3)]
    truth = make_folder(tmp_path / "rec", naming="timestamp", intrinsics="intrinsics.json", masks=False,
                        poses=[(100.0, P[0]), (100.1, P[1]), (100.2, P[2])], rgb_ext=".jpg")
    ds = FolderSequence(tmp_path / "rec", depth_scale=1000)
    assert ds.timestamp_source == "names" and not ds.has_masks and ds.has_gt_poses
    np.testing.assert_allclose(ds.timestamps, [100.0, 100.1, 100.2])
    assert ds.gt_valid.all()
    for i in range(3):
        np.testing.assert_allclose(ds[i].gt_pose.numpy(), P[i], atol=1e-9)
        decoded = cv2.imread(str(tmp_path / "rec" / "rgb" / f"{truth.stems[i]}.jpg"))[:, :, ::-1]  # lossy: compare to decoder
        np.testing.assert_array_equal(np.round(ds[i].rgb.numpy() * 255).astype(np.uint8), decoded)


def test_timestamps_file_and_partial_poses(tmp_path):
    make_folder(tmp_path / "rec", n=3, timestamps_txt=[5.0, 5.5, 7.0], poses=[(5.0, np.eye(4)), (5.5, np.eye(4))])
    ds = FolderSequence(tmp_path / "rec")
    assert ds.timestamp_source == "file"
    np.testing.assert_allclose(ds.timestamps, [5.0, 5.5, 7.0])
    assert ds.gt_valid.tolist() == [True, True, False]
    assert ds[2].gt_pose is None
    assert FolderSequence(tmp_path / "rec", timestamps_from="fps", fps=2.0).timestamps.tolist() == [0, 0.5, 1.0]


def test_last_frame_keeps_its_pose_with_rounded_pose_times(tmp_path):
    # Frames at index / fps (1/30 s = 0.0333333...) and poses.txt rounded to 6 decimals (0.033333):
    # the last frame lies just after the last pose and used to lose its ground truth.
    rng = np.random.default_rng(4)
    P = [random_pose(rng) for _ in range(2)]
    make_folder(tmp_path / "rec", n=2, masks=False, poses=[(0.0, P[0]), (1 / 30, P[1])])
    ds = FolderSequence(tmp_path / "rec", fps=30.0)
    assert ds.timestamps[-1] > float(f"{1 / 30:.6f}")
    assert ds.gt_valid.tolist() == [True, True]
    for i in range(2):
        np.testing.assert_allclose(ds[i].gt_pose.numpy(), P[i], atol=1e-9)


def test_config_intrinsics(tmp_path):
    make_folder(tmp_path / "rec", intrinsics=None)
    with pytest.raises(DatasetError, match=r"intrinsics\.txt: not found"):
        FolderSequence(tmp_path / "rec")
    ds = FolderSequence(tmp_path / "rec", intrinsics={"fx": 7, "fy": 8, "cx": 9, "cy": 10})
    assert (ds.intrinsics.fx, ds.intrinsics.width) == (7.0, W)


# ----------------------------------------------------------------------------------- bad input


def test_missing_root_and_subfolder(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: sequence folder not found"):
        FolderSequence(tmp_path / "nowhere")
    make_folder(tmp_path / "rec")
    shutil.rmtree(tmp_path / "rec" / "depth")
    with pytest.raises(DatasetError, match=r"rec/depth: depth folder not found"):
        FolderSequence(tmp_path / "rec")


def test_missing_frame_in_middle(tmp_path):
    make_folder(tmp_path / "rec", n=4)
    (tmp_path / "rec" / "depth" / "2.png").unlink()
    with pytest.raises(DatasetError, match=r"depth/2\.png: missing \(colour image 2\.png exists\)"):
        FolderSequence(tmp_path / "rec")
    make_folder(tmp_path / "r2", n=4)
    (tmp_path / "r2" / "masks" / "1.png").unlink()
    with pytest.raises(DatasetError, match=r"masks/1\.png: missing"):
        FolderSequence(tmp_path / "r2")


def test_unreadable_png_and_size_mismatch(tmp_path):
    make_folder(tmp_path / "rec", n=3)
    (tmp_path / "rec" / "depth" / "1.png").write_text("hello")
    write_png_rgb(tmp_path / "rec" / "rgb" / "2.png", np.zeros((H - 1, W, 3), np.uint8))
    ds = FolderSequence(tmp_path / "rec")
    with pytest.raises(DatasetError, match=r"depth/1\.png: cannot decode image"):
        ds[1]
    with pytest.raises(DatasetError, match=rf"depth/2\.png: depth is {W}x{H} but colour 2\.png is {W}x{H - 1}"):
        ds[2]
    write_png8(tmp_path / "rec" / "masks" / "0.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(DatasetError, match=rf"masks/0\.png: mask is 4x4 but the sequence is {W}x{H}"):
        ds[0]


def test_bad_timestamps(tmp_path):
    make_folder(tmp_path / "rec", n=3, timestamps_txt=[1.0, 3.0, 2.0])
    with pytest.raises(DatasetError, match=r"timestamps\.txt: timestamps are not strictly increasing at entry 2"):
        FolderSequence(tmp_path / "rec")
    (tmp_path / "rec" / "timestamps.txt").write_text("1\n2\n")
    with pytest.raises(DatasetError, match=r"timestamps\.txt: has 2 timestamps but rgb/ has 3 images"):
        FolderSequence(tmp_path / "rec")
    with pytest.raises(DatasetError, match=r"file name is not a timestamp"):
        FolderSequence(tmp_path / "rec", timestamps_from="names")


def test_principal_point_outside_the_image(tmp_path):
    make_folder(tmp_path / "rec")
    (tmp_path / "rec" / "intrinsics.txt").write_text("20 21 5000 11.5\n")
    with pytest.raises(DatasetError, match=rf"intrinsics\.txt: principal point \(cx=5000, cy=11\.5\) is outside the {W}x{H} image"):
        FolderSequence(tmp_path / "rec")
    with pytest.raises(DatasetError, match=r"^dataset\.intrinsics: principal point \(cx=1, cy=-7\) is outside"):
        FolderSequence(tmp_path / "rec", intrinsics={"fx": 5, "fy": 5, "cx": 1, "cy": -7})


def test_malformed_poses_and_intrinsics(tmp_path):
    make_folder(tmp_path / "rec", poses=[(0.0, np.eye(4))])
    (tmp_path / "rec" / "poses.txt").write_text("# t\n0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1 9\n")
    with pytest.raises(DatasetError, match=r"poses\.txt:3: expected 8 fields"):
        FolderSequence(tmp_path / "rec")
    (tmp_path / "rec" / "poses.txt").unlink()
    (tmp_path / "rec" / "intrinsics.txt").write_text("20 21\n")
    with pytest.raises(DatasetError, match=r"intrinsics\.txt:1: expected 4 to 6 fields"):
        FolderSequence(tmp_path / "rec")


def test_config_instantiates(tmp_path):
    from fixtures import instantiate_dataset

    truth = make_folder(tmp_path / "rec")
    ds = instantiate_dataset("folder", tmp_path / "rec")
    assert isinstance(ds, FolderSequence) and ds.name == "folder" and len(ds) == 3
    np.testing.assert_allclose(ds[1].depth.numpy(), truth.depth[1], rtol=1e-7)
    ds = instantiate_dataset("folder", tmp_path / "rec", intrinsics={"fx": 5, "fy": 5, "cx": 1, "cy": 1})
    assert ds.intrinsics.fx == 5
    with pytest.raises(DatasetError, match=r"wrong: sequence folder not found"):
        instantiate_dataset("folder", tmp_path / "wrong")


def test_inspect_summarize(tmp_path):
    from data_modules.inspect import summarize

    truth = make_folder(tmp_path / "rec", n=4, timestamps_txt=[0, 0.1, 0.2, 0.3], poses=[(0.0, np.eye(4)), (0.3, np.eye(4))])
    s = summarize(FolderSequence(tmp_path / "rec", pose_max_gap=None))
    valid = sum(int((d > 0).sum()) for d in truth.depth) / (4 * W * H)
    dyn = sum(int(m.sum()) for m in truth.masks) / (4 * W * H)
    assert (s["frames"], s["width"], s["height"]) == (4, W, H)
    assert s["has_gt_poses"] and s["has_masks"]
    assert s["valid_depth_pct"] == pytest.approx(100 * valid)
    assert s["dynamic_pct"] == pytest.approx(100 * dyn)
    assert s["duration_s"] == pytest.approx(0.3)


def test_inspect_cli_body_json(tmp_path, capsys):
    import json

    from fixtures import run_inspect_inprocess

    make_folder(tmp_path / "rec", n=3)
    assert run_inspect_inprocess("dataset=folder", f"dataset.root={tmp_path / 'rec'}", "format=json") == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (s["name"], s["frames"], s["width"], s["height"], s["has_masks"], s["has_gt_poses"]) == ("folder", 3, W, H, True, False)
    assert s["fps"] == pytest.approx(30.0)
    (tmp_path / "rec" / "rgb" / "1.png").write_bytes(b"junk")
    assert run_inspect_inprocess("dataset=folder", f"dataset.root={tmp_path / 'rec'}") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("rgb/1.png: cannot decode image (not a valid PNG/JPEG file?)")
