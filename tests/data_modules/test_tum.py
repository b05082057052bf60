"""TUM RGB-D and Bonn readers on tiny self-written sequences."""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
import fixtures  # noqa: E402
from fixtures import TUM_H, TUM_W, make_tum, random_pose, write_png_rgb  # noqa: E402

from data_modules.frame import DatasetError  # noqa: E402
from data_modules.tum import (  # noqa: E402
    T_M,
    T_M_RAW,
    T_ROS,
    BonnSequence,
    TUMSequence,
)

T0 = 1341846313.5
W, H = TUM_W, TUM_H  # the camera presets' image size


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(axis * angle)
    return R


def _pose(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def test_round_trip_association_and_intrinsics(tmp_path):
    truth = make_tum(tmp_path / "rgbd_dataset_freiburg3_walking_xyz", n=6)
    ds = TUMSequence(tmp_path / "rgbd_dataset_freiburg3_walking_xyz")
    assert ds.name == "rgbd_dataset_freiburg3_walking_xyz"
    assert truth.matched == [0, 1, 2, 4, 5] and len(ds) == 5 and ds.dropped_rgb == 1
    np.testing.assert_array_equal(ds.timestamps, truth.rgb_ts)
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height, k.readout_s) == (535.4, 539.2, 320.1, 247.6, W, H, 0.0)
    assert TUMSequence(tmp_path / "rgbd_dataset_freiburg3_walking_xyz", readout_s=0.03).intrinsics.readout_s == 0.03
    assert not ds.undistort and not ds.has_gt_poses and not ds.has_masks
    for i in range(len(ds)):
        f = ds[i]
        np.testing.assert_array_equal(np.round(f.rgb.numpy() * 255).astype(np.uint8), truth.rgb[i])
        np.testing.assert_allclose(f.depth.numpy(), truth.depth[i], rtol=1e-7)
        assert f.gt_pose is None and f.mask is None and f.timestamp == truth.rgb_ts[i]
        assert f.source == ds.rgb_paths[i].name  # the colour file, for per-frame side files (mask PNGs)


def test_max_time_diff_configurable(tmp_path):
    make_tum(tmp_path / "s", n=4)
    assert len(TUMSequence(tmp_path / "s", max_time_diff=0.6)) == 4
    assert len(TUMSequence(tmp_path / "s", max_time_diff=0.012)) == 2


def test_camera_presets_and_overrides(tmp_path):
    make_tum(tmp_path / "s", n=2)
    k = TUMSequence(tmp_path / "s", camera="fr1", undistort=False).intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (517.3, 516.5, 318.6, 255.3)
    ds = TUMSequence(tmp_path / "s", camera="fr2", fx=100.0, width=W, height=H)
    assert (ds.intrinsics.fx, ds.intrinsics.fy) == (100.0, 521.0) and ds.undistort
    ds = TUMSequence(tmp_path / "s", camera="custom", fx=1, fy=2, cx=3, cy=4)
    assert (ds.intrinsics.cx, ds.intrinsics.cy) == (3, 4)
    with pytest.raises(DatasetError, match="camera=custom needs fx, fy, cx and cy"):
        TUMSequence(tmp_path / "s", camera="custom", fx=1)
    with pytest.raises(DatasetError, match="dataset.camera: unknown camera 'fr9'"):
        TUMSequence(tmp_path / "s", camera="fr9")


def test_undistort_matches_opencv(tmp_path):
    truth = make_tum(tmp_path / "s", n=2, size=(fixtures.W, fixtures.H))  # small image, custom K
    dist = [0.3, -0.1, 0.01, -0.01, 0.0]
    kw = dict(camera="custom", fx=20.0, fy=20.0, cx=15.5, cy=11.5, distortion=dist)
    raw = TUMSequence(tmp_path / "s", undistort=False, **kw)[0]
    und = TUMSequence(tmp_path / "s", **kw)[0]
    K = np.array([[20.0, 0, 15.5], [0, 20.0, 11.5], [0, 0, 1]])
    expect = cv2.undistort(truth.rgb[0].astype(np.float32) / 255, K, np.array(dist))
    diff = np.abs(und.rgb.numpy() - np.clip(expect, 0, 1))  # cv2.undistort uses fixed-point maps
    assert diff.max() < 0.03 and diff.mean() < 3e-3
    np.testing.assert_array_equal(raw.depth.numpy(), truth.depth[0])
    assert not np.array_equal(und.depth.numpy(), raw.depth.numpy())
    # nearest-neighbour depth: every output value is an input value or invalid (0)
    assert set(np.unique(und.depth.numpy())) <= set(np.unique(truth.depth[0])) | {0.0}
    assert (und.depth.numpy() == 0).any()


def test_gt_interpolation_gaps_and_coverage(tmp_path):
    R0, R1 = _rot([1, 2, 3], 0.2), _rot([1, 2, 3], 0.8)
    A = _pose(R0, [0, 0, 0])
    B = _pose(R1, [0.6, -0.3, 1.2])
    C = _pose(np.eye(3), [5, 5, 5])
    gt = [(T0 - 0.01, A), (T0 + 0.05, B), (T0 + 0.3, C)]
    make_tum(tmp_path / "s", n=3, gt=gt)
    ds = TUMSequence(tmp_path / "s")
    assert ds.has_gt_poses
    assert ds.gt_valid.tolist() == [True, True, False]
    for i in range(2):
        s = (ds.timestamps[i] - (T0 - 0.01)) / 0.06
        expect = _pose(_rot([1, 2, 3], 0.2 + 0.6 * s), s * B[:3, 3])
        np.testing.assert_allclose(ds[i].gt_pose.numpy(), expect, atol=1e-6)
        assert ds[i].gt_pose.dtype == torch.float64
    assert ds[2].gt_pose is None
    assert TUMSequence(tmp_path / "s", gt_max_gap=None).gt_valid.tolist() == [True, True, True]
    assert ds.describe()["gt_valid_frames"] == 2


def test_gt_starting_late_is_not_extrapolated(tmp_path):
    gt = [(T0 + 0.02, np.eye(4)), (T0 + 0.1, np.eye(4))]
    make_tum(tmp_path / "s", n=3, gt=gt)
    assert TUMSequence(tmp_path / "s").gt_valid.tolist() == [False, True, True]


def test_bonn_marker_to_camera(tmp_path):
    rng = np.random.default_rng(3)
    cams = [random_pose(rng) for _ in range(3)]
    ts = [T0 + k / 30 for k in range(3)]
    # invert T_cam = T_ros T_gt T_ros T_m  ->  T_gt = T_ros T_cam T_m^-1 T_ros
    gt = [(float(f"{t:.6f}"), T_ROS @ C @ np.linalg.inv(T_M) @ T_ROS) for t, C in zip(ts, cams)]
    make_tum(tmp_path / "rgbd_bonn_balloon", n=3, gt=gt, depth_offsets=(0.001,))
    ds = BonnSequence(tmp_path / "rgbd_bonn_balloon")
    k = ds.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy) == (542.822841, 542.576870, 315.593520, 237.756098)
    assert ds.undistort and ds.gt_valid.all() and ds.describe()["marker_to_camera"]
    for i in range(3):
        np.testing.assert_allclose(ds[i].gt_pose.numpy(), cams[i], atol=1e-9)
    raw = BonnSequence(tmp_path / "rgbd_bonn_balloon", marker_to_camera=False)
    np.testing.assert_allclose(raw[0].gt_pose.numpy(), gt[0][1], atol=1e-9)


def test_bonn_constants():
    R = T_M[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    sv = np.linalg.svd(T_M_RAW[:3, :3], compute_uv=False)
    np.testing.assert_allclose(sv, 1.0593, atol=2e-3)
    np.testing.assert_allclose(R, T_M_RAW[:3, :3] / sv.mean(), atol=5e-3)
    np.testing.assert_array_equal(T_M[:3, 3], T_M_RAW[:3, 3])
    np.testing.assert_array_equal(T_ROS @ T_ROS, np.eye(4))


# ----------------------------------------------------------------------------------- bad input


def test_missing_root_and_list_file(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: TUMSequence sequence folder not found"):
        TUMSequence(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match=r"nowhere: BonnSequence sequence folder not found"):
        BonnSequence(tmp_path / "nowhere")
    make_tum(tmp_path / "s", n=2)
    (tmp_path / "s" / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth\.txt: depth\.txt not found"):
        TUMSequence(tmp_path / "s")


def test_missing_frame_in_middle(tmp_path):
    make_tum(tmp_path / "s", n=4)
    victim = sorted((tmp_path / "s" / "rgb").iterdir())[1]
    victim.unlink()
    with pytest.raises(DatasetError, match=rf"{victim.name}: missing \(listed in rgb\.txt:5\)"):
        TUMSequence(tmp_path / "s")


def test_unreadable_png_and_size_mismatch(tmp_path):
    make_tum(tmp_path / "s", n=3)
    d = sorted((tmp_path / "s" / "depth").iterdir())
    d[0].write_bytes(b"\x89PNG nope")
    ds = TUMSequence(tmp_path / "s")
    with pytest.raises(DatasetError, match=rf"{d[0].name}: cannot decode image"):
        ds[0]
    r = sorted((tmp_path / "s" / "rgb").iterdir())
    write_png_rgb(r[1], np.zeros((H, W + 4, 3), np.uint8))
    with pytest.raises(DatasetError, match=rf"{d[1].name}: depth is {W}x{H} but colour {r[1].name} is {W + 4}x{H}"):
        ds[1]


def test_non_monotonic_timestamps(tmp_path):
    make_tum(tmp_path / "s", n=3)
    p = tmp_path / "s" / "rgb.txt"
    lines = p.read_text().splitlines()
    lines[3], lines[4] = lines[4], lines[3]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt: timestamps are not strictly increasing at entry 1"):
        TUMSequence(tmp_path / "s")


def test_malformed_list_and_groundtruth(tmp_path):
    make_tum(tmp_path / "s", n=2, gt=[(T0, np.eye(4)), (T0 + 0.1, np.eye(4))])
    gt = tmp_path / "s" / "groundtruth.txt"
    gt.write_text(gt.read_text() + "1341846314.0 1 2 3 4 5 6\n")
    with pytest.raises(DatasetError, match=r"groundtruth\.txt:6: expected 8 fields \(timestamp tx ty tz qx qy qz qw\), got 7"):
        TUMSequence(tmp_path / "s")
    (tmp_path / "s" / "rgb.txt").write_text("# c\nabc rgb/x.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt:2: bad timestamp 'abc'"):
        TUMSequence(tmp_path / "s")


def test_principal_point_outside_the_image(tmp_path, capsys):
    from fixtures import run_inspect_inprocess

    make_tum(tmp_path / "s", n=2)
    with pytest.raises(DatasetError, match=r"^dataset \(camera fr3\): principal point \(cx=5000, cy=247\.6\) is outside the 640x480 image"):
        TUMSequence(tmp_path / "s", cx=5000)
    make_tum(tmp_path / "small", n=2, size=(80, 60))  # fr3 intrinsics on a downscaled recording
    with pytest.raises(DatasetError, match=r"^dataset \(camera fr3\): principal point \(cx=320\.1, cy=247\.6\) is outside the 80x60"):
        TUMSequence(tmp_path / "small")
    # end to end: one line, exit 2 (it used to run to an identity trajectory)
    assert run_inspect_inprocess("dataset=tum", f"dataset.root={tmp_path / 's'}", "dataset.cx=5000") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: dataset (camera fr3): principal point (cx=5000, cy=247.6) is outside the 640x480 image (intrinsics for another image size?)"]


def test_no_association(tmp_path):
    make_tum(tmp_path / "s", n=2, depth_offsets=(0.5,))
    with pytest.raises(DatasetError, match=r"rgb\.txt: no colour image has a depth image within 0\.02 s"):
        TUMSequence(tmp_path / "s")


@pytest.mark.parametrize("config,cls", [("tum", TUMSequence), ("bonn", BonnSequence)])
def test_config_instantiates(tmp_path, config, cls):
    from fixtures import instantiate_dataset

    make_tum(tmp_path / "seq", n=3, gt=[(T0 - 0.04, np.eye(4)), (T0 + 0.04, np.eye(4)), (T0 + 0.12, np.eye(4))])
    ds = instantiate_dataset(config, tmp_path / "seq")
    assert type(ds) is cls and ds.name == config and len(ds) == 3 and ds.gt_valid.all()
    assert ds[0].rgb.shape == (H, W, 3)
    fr1 = instantiate_dataset("tum", tmp_path / "seq", camera="fr1")
    assert fr1.intrinsics.fx == 517.3 and fr1.undistort
    with pytest.raises(DatasetError, match=r"wrong: .*Sequence sequence folder not found"):
        instantiate_dataset(config, tmp_path / "wrong")


def test_inspect_summarize_and_cli(tmp_path, capsys):
    import json

    from fixtures import run_inspect_inprocess

    from data_modules.inspect import summarize

    truth = make_tum(tmp_path / "seq", n=3, gt=[(T0 + 0.02, np.eye(4)), (T0 + 0.1, np.eye(4))])
    valid = sum(int((d > 0).sum()) for d in truth.depth) / (3 * W * H)
    for cls in (TUMSequence, BonnSequence):
        s = summarize(cls(tmp_path / "seq", undistort=False))
        assert (s["frames"], s["width"], s["height"]) == (3, W, H)
        assert s["has_gt_poses"] and not s["has_masks"]
        assert s["valid_depth_pct"] == pytest.approx(100 * valid)
    status = run_inspect_inprocess("dataset=bonn", f"dataset.root={tmp_path / 'seq'}", "dataset.undistort=false", "format=json")
    out = capsys.readouterr()
    assert status == 0, out.err
    cli = json.loads(out.out.strip().splitlines()[-1])
    assert (cli["frames"], cli["height"], cli["has_gt_poses"]) == (3, H, True)
    assert cli["valid_depth_pct"] == pytest.approx(100 * valid)
