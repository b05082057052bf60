"""The data contract: Frame validation and Intrinsics."""

from __future__ import annotations

import pytest
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics, intrinsics_from


def _frame(h=4, w=5) -> Frame:
    return Frame(0, 0.0, torch.full((h, w, 3), 0.5), torch.ones(h, w), torch.zeros(h, w, dtype=torch.bool), torch.eye(4))


def test_valid_frame_passes():
    f = _frame()
    assert f.validate("x") is f
    assert (f.height, f.width) == (4, 5)
    f.validate("x", Intrinsics(5, 5, 2, 1.5, 5, 4))


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(depth=torch.ones(4, 5, 1)), "depth must be"),
        (dict(rgb=torch.full((4, 5), 0.5)), "rgb shape"),
        (dict(rgb=torch.full((4, 6, 3), 0.5)), "does not match depth"),
        (dict(depth=torch.ones(4, 5, dtype=torch.float64)), "float32"),
        (dict(depth=torch.where(torch.eye(4, 5, dtype=torch.bool), float("nan"), 1.0)), "NaN"),
        (dict(depth=-torch.ones(4, 5)), "negative"),
        (dict(rgb=torch.full((4, 5, 3), 1.5)), r"\[0, 1\]"),
        (dict(mask=torch.zeros(4, 5, dtype=torch.uint8)), "mask"),
        (dict(mask=torch.zeros(3, 5, dtype=torch.bool)), "mask"),
        (dict(instances=torch.zeros(4, 5, dtype=torch.int32)), "instances"),
        (dict(instances=torch.zeros(4, 6, dtype=torch.int64)), "instances"),
        (dict(instances=-torch.ones(4, 5, dtype=torch.int64)), "instance ids"),
        (dict(gt_pose=torch.eye(3)), "gt_pose"),
        (dict(gt_pose=torch.full((4, 4), float("inf"))), "gt_pose"),
        (dict(timestamp=float("nan")), "timestamp"),
    ],
)
def test_validate_rejects_bad_frames(change, message):
    f = _frame()
    for k, v in change.items():
        setattr(f, k, v)
    with pytest.raises(DatasetError, match=message) as err:
        f.validate("frames/0001.png")
    assert str(err.value).startswith("frames/0001.png: ") and "\n" not in str(err.value)


def test_validate_checks_intrinsics_size():
    with pytest.raises(DatasetError, match="intrinsics are for 6x4"):
        _frame().validate("x", Intrinsics(5, 5, 2, 1.5, 6, 4))


def test_intrinsics_checks_and_resize():
    with pytest.raises(DatasetError, match="focal"):
        Intrinsics(0, 1, 0, 0, 4, 4)
    with pytest.raises(DatasetError, match="finite"):
        Intrinsics(1, 1, float("nan"), 0, 4, 4)
    with pytest.raises(DatasetError, match="size"):
        Intrinsics(1, 1, 0, 0, 0, 4)
    K = Intrinsics(500.0, 400.0, 319.5, 239.5, 640, 480)
    half = K.resized(320, 240)
    assert (half.fx, half.fy, half.cx, half.cy, half.width, half.height) == (250.0, 200.0, 159.5, 119.5, 320, 240)
    assert K.resized(640, 480) == K
    assert torch.equal(K.K(), torch.tensor([[500.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]]))
    assert K.as_dict()["width"] == 640


def test_a_rolling_shutters_readout_is_checked_and_kept_by_a_resize():
    K = Intrinsics(500.0, 400.0, 319.5, 239.5, 640, 480, readout_s=0.03)
    assert K.resized(320, 240).readout_s == 0.03 and K.as_dict()["readout_s"] == 0.03
    assert Intrinsics(500.0, 400.0, 319.5, 239.5, 640, 480).readout_s == 0.0  # a global shutter unless said
    for bad in (-0.01, 1.5, float("nan")):
        with pytest.raises(DatasetError, match=r"^intrinsics: readout_s must be in \[0, 1\) seconds"):
            Intrinsics(500.0, 400.0, 319.5, 239.5, 640, 480, readout_s=bad)
    with pytest.raises(DatasetError, match=r"^dataset: fx, fy, cx, cy, width, height, readout_s must be numbers"):
        intrinsics_from("dataset", 525, 525, 320, 240, 640, 480, readout_s="fast")


def test_principal_point_must_lie_in_the_image():
    # the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5] (pixel centres at integers)
    Intrinsics(500.0, 500.0, -0.5, -0.5, 640, 480)
    Intrinsics(500.0, 500.0, 639.5, 479.5, 640, 480)
    for cx, cy in ((5000.0, 240.0), (320.0, -3.0), (639.6, 240.0), (320.0, 480.0)):
        with pytest.raises(DatasetError, match=r"^intrinsics: principal point \(cx=.*\) is outside the 640x480 image") as err:
            Intrinsics(500.0, 500.0, cx, cy, 640, 480)
        assert "\n" not in str(err.value)


def test_intrinsics_from_names_the_source():
    k = intrinsics_from("dataset", "525", 525, 319.5, 239.5, 640.0, 480)
    assert k == Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    with pytest.raises(DatasetError, match=r"^dataset\.intrinsics: principal point \(cx=5000, cy=240\) is outside the 640x480 image"):
        intrinsics_from("dataset.intrinsics", 525, 525, 5000, 240, 640, 480)
    with pytest.raises(DatasetError, match=r"^cam\.txt: fy must be finite, got nan"):
        intrinsics_from("cam.txt", 525, float("nan"), 320, 240, 640, 480)
    with pytest.raises(DatasetError, match=r"^dataset: fx, fy, cx, cy, width, height, readout_s must be numbers"):
        intrinsics_from("dataset", "abc", 525, 320, 240, 640, 480)
