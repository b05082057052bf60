"""The colour camera of unregistered colour: estimated from depth edges, applied by the TUM reader."""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from fixtures import make_tum  # noqa: E402

from data_modules.frame import DatasetError  # noqa: E402
from data_modules.registration import edge_frame, estimate_colour_camera  # noqa: E402
from data_modules.synthetic import SyntheticSequence  # noqa: E402
from data_modules.tum import TUMSequence  # noqa: E402


def _colour_map(K: np.ndarray, Kc: np.ndarray, size: tuple[int, int]):
    """For each pixel of a colour camera Kc, the pixel of camera K that sees the same ray."""
    return cv2.initUndistortRectifyMap(K, np.zeros(5), None, Kc, size, cv2.CV_32FC1)


def test_a_colour_camera_with_another_focal_length_is_recovered_from_depth_edges():
    seq = SyntheticSequence(scene="cube", num_frames=30, width=320, height=240)
    intr = seq.intrinsics
    K = intr.K(dtype=torch.float64).numpy()
    Kc = np.array([[0.9 * K[0, 0], 0, K[0, 2] - 3], [0, 0.9 * K[1, 1], K[1, 2] + 2], [0, 0, 1.0]])
    maps = _colour_map(K, Kc, (intr.width, intr.height))
    evidence = []
    for i in range(0, 30, 3):  # the colour a camera Kc would see: not registered to the depth
        f = seq[i]
        raw = cv2.remap(f.rgb.numpy(), maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        evidence.append(edge_frame(raw, f.depth.numpy(), intr))
    est = estimate_colour_camera(evidence, intr)
    fx, fy, cx, cy = est.colour_camera
    assert abs(fx / Kc[0, 0] - 1) < 0.03 and abs(fy / Kc[1, 1] - 1) < 0.03  # 10 % off to start with
    assert abs(cx - Kc[0, 2]) < 3 and abs(cy - Kc[1, 2]) < 3
    assert est.contrast_estimated > est.contrast_registered
    with pytest.raises(ValueError, match="no depth edges"):
        estimate_colour_camera([edge_frame(raw, np.ones_like(f.depth.numpy()), intr)], intr)


def test_the_tum_reader_resamples_colour_onto_the_depth_pixels(tmp_path):
    make_tum(tmp_path / "s", n=2)
    plain = TUMSequence(tmp_path / "s", camera="ros")
    K = plain.intrinsics.K(dtype=torch.float64).numpy()
    Kc = [0.9 * K[0, 0], 0.9 * K[1, 1], K[0, 2] + 4, K[1, 2] - 2]
    reg = TUMSequence(tmp_path / "s", camera="ros", colour_camera=Kc)
    Kcm = np.array([[Kc[0], 0, Kc[2]], [0, Kc[1], Kc[3]], [0, 0, 1.0]])
    mx, my = cv2.initUndistortRectifyMap(Kcm, np.zeros(5), None, K, (plain.intrinsics.width, plain.intrinsics.height), cv2.CV_32FC1)
    expect = cv2.remap(plain[0].rgb.numpy(), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    np.testing.assert_allclose(reg[0].rgb.numpy(), expect, atol=1e-6)
    np.testing.assert_array_equal(reg[0].depth.numpy(), plain[0].depth.numpy())  # depth is the reference
    assert reg.describe()["colour_camera"] == Kc
    with pytest.raises(DatasetError, match=r"dataset.colour_camera: must be \[fx, fy, cx, cy\]"):
        TUMSequence(tmp_path / "s", camera="ros", colour_camera=[500.0, 0.0, 320.0, 240.0])


def test_the_tum_reader_takes_each_pixels_colour_at_its_own_parallax(tmp_path):
    make_tum(tmp_path / "s", n=2)
    plain = TUMSequence(tmp_path / "s", camera="ros")
    K = plain.intrinsics.K(dtype=torch.float64).numpy()
    Kc = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    reg = TUMSequence(tmp_path / "s", camera="ros", colour_camera=Kc, colour_offset=[0.03, -0.01])
    depth = plain[0].depth.numpy()
    assert (depth > 0).any()
    u, v = np.meshgrid(np.arange(depth.shape[1], dtype=np.float32), np.arange(depth.shape[0], dtype=np.float32))
    z = np.where(depth > 0, depth, np.median(depth[depth > 0]))
    mx, my = u - K[0, 0] * 0.03 / z, v + K[1, 1] * 0.01 / z
    expect = cv2.remap(plain[0].rgb.numpy(), mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    np.testing.assert_allclose(reg[0].rgb.numpy(), expect, atol=1e-3)  # the maps' float rounding
    assert np.abs(reg[0].rgb.numpy() - plain[0].rgb.numpy()).max() > 0.1  # the parallax moved the colour
    assert reg.describe()["colour_offset"] == [0.03, -0.01]
    with pytest.raises(DatasetError, match="dataset.colour_offset: needs dataset.colour_camera"):
        TUMSequence(tmp_path / "s", camera="ros", colour_offset=[0.03, 0.0])
    with pytest.raises(DatasetError, match=r"dataset.colour_offset: must be \[x, y\]"):
        TUMSequence(tmp_path / "s", camera="ros", colour_camera=Kc, colour_offset=[0.03])
