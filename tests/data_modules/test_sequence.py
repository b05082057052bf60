"""The data contract's sequences: SequenceDataset, SequenceView and SequenceDataModule."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError, Frame, Intrinsics
from data_modules.sequence import SequenceDataModule, SequenceDataset, SequenceView


class _Ramp(SequenceDataset):
    """In-memory sequence: frame i has depth = 1 + i + column / 10, a dynamic left half and pose x = i."""

    def __init__(self, n: int = 10, width: int = 8, height: int = 6, masks: bool = True) -> None:
        self.name = "ramp"
        self.intrinsics = Intrinsics(10.0, 10.0, (width - 1) / 2, (height - 1) / 2, width, height)
        self.timestamps = np.arange(n) * 0.1 + 5.0
        self.has_gt_poses = True
        self.has_masks = masks
        self.reads: list[int] = []

    def load_frame(self, i: int) -> Frame:
        self.reads.append(i)
        h, w = self.intrinsics.height, self.intrinsics.width
        depth = (1.0 + i + torch.arange(w, dtype=torch.float32) / 10).expand(h, w).contiguous()
        rgb = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(i))
        mask = None
        if self.has_masks:
            mask = torch.zeros(h, w, dtype=torch.bool)
            mask[:, : w // 2] = True
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = i
        return Frame(i, float(self.timestamps[i]), rgb, depth, mask, pose).validate(f"ramp {i}", self.intrinsics)


def test_view_stride_and_max_frames():
    base = _Ramp(10)
    view = SequenceView(base, stride=3, max_frames=3)
    assert len(view) == 3 and list(view.source_indices) == [0, 3, 6]
    assert np.allclose(view.timestamps, [5.0, 5.3, 5.6])
    assert [view[i].index for i in range(3)] == [0, 3, 6]
    assert view.name == "ramp" and view.has_gt_poses and view.has_masks and view.intrinsics == base.intrinsics
    assert len(SequenceView(base, stride=4)) == 3
    assert view.describe()["frames"] == 3
    with pytest.raises(IndexError):
        view[3]
    for kwargs, param in (
        (dict(stride=0), "data.stride"),
        (dict(max_frames=0), "data.max_frames"),
        (dict(depth_min=1.0, depth_max=0.5), "data.depth_max"),
        (dict(resize=[10]), "data.resize"),
        (dict(resize=[0, 4]), "data.resize"),
    ):
        with pytest.raises(DatasetError, match=param):
            SequenceView(base, **kwargs)


def test_view_starts_at_first_frame_before_the_stride():
    base = _Ramp(10)
    view = SequenceView(base, first_frame=4, stride=2, max_frames=2)
    assert list(view.source_indices) == [4, 6] and [view[i].index for i in range(2)] == [4, 6]
    assert np.allclose(view.timestamps, [5.4, 5.6])
    assert list(SequenceView(base, first_frame=9).source_indices) == [9]
    frames = list(SequenceDataModule(base, first_frame=7).train_dataloader())
    assert [f.index for f in frames] == [7, 8, 9] and [float(f.gt_pose[0, 3]) for f in frames] == [7.0, 8.0, 9.0]
    for bad, message in ((10, "below the sequence's 10 frames, got 10"), (-1, ">= 0"), (1.5, ">= 0"), (True, ">= 0")):
        with pytest.raises(DatasetError, match=message):
            SequenceView(base, first_frame=bad)


def test_view_leaves_out_a_dropped_stretch():
    base = _Ramp(10)
    view = SequenceView(base, drop_frames=[3, 6])
    assert list(view.source_indices) == [0, 1, 2, 7, 8, 9] and view[3].index == 7
    assert list(SequenceView(base, first_frame=2, stride=2, drop_frames=[4, 4], max_frames=3).source_indices) == [2, 6, 8]
    for bad in ([5, 3], [2], [-1, 3], [1.5, 3], [True, 3]):
        with pytest.raises(DatasetError, match="data.drop_frames"):
            SequenceView(base, drop_frames=bad)
    with pytest.raises(DatasetError, match=r"\[0, 9\] leaves none of the 10 frames"):
        SequenceView(base, drop_frames=[0, 9])


def test_view_resize_scales_intrinsics_and_uses_nearest_mask():
    base = _Ramp(2, width=8, height=6)
    view = SequenceView(base, resize=[4, 3])
    assert view.intrinsics == base.intrinsics.resized(4, 3)
    f = view[1]
    f.validate("resized", view.intrinsics)
    assert f.rgb.shape == (3, 4, 3) and f.depth.shape == (3, 4) and f.mask.shape == (3, 4)
    assert f.mask.dtype == torch.bool and f.mask[:, :2].all() and not f.mask[:, 2:].any()
    # Nearest depth: every output value is one of the input values (no mixing across edges).
    src = base[1].depth
    assert all(bool((src == v).any()) for v in f.depth.flatten())
    assert torch.allclose(f.rgb.mean(), base[1].rgb.mean(), atol=1e-5)  # area averaging keeps the mean
    assert f.instances is None  # a reader without instance ids keeps working


def test_resize_keeps_instance_ids_nearest():
    from dataclasses import replace

    from data_modules.sequence import resize_frame

    frame = _Ramp(1, width=8, height=6)[0]
    ids = torch.zeros(6, 8, dtype=torch.int64)
    ids[:, :4], ids[:3, 6:] = 7, 300
    small = resize_frame(replace(frame, instances=ids), 4, 3)
    small.validate("resized")
    expected = torch.zeros(3, 4, dtype=torch.int64)
    expected[:, :2] = 7
    expected[:1, 3:] = 300  # nearest-exact: output row 1 samples input row 3 (outside the 300 block)
    assert torch.equal(small.instances, expected)


def test_view_depth_truncation():
    base = _Ramp(3, width=10)
    view = SequenceView(base, depth_min=1.25, depth_max=1.65)
    d = view[0].depth[0]  # 1.0 .. 1.9
    assert torch.equal(d == 0, (base[0].depth[0] < 1.25) | (base[0].depth[0] > 1.65))
    assert (d[d > 0] >= 1.25).all() and (d <= 1.65).all()
    assert torch.equal(SequenceView(base)[0].depth, base[0].depth)


def test_datamodule_yields_frames_in_order():
    base = _Ramp(7, masks=False)
    dm = SequenceDataModule(base, stride=2, max_frames=3)
    assert dm.intrinsics == base.intrinsics
    frames = list(dm.train_dataloader())
    assert all(isinstance(f, Frame) for f in frames)
    assert [f.index for f in frames] == [0, 2, 4]
    assert [f.timestamp for f in frames] == pytest.approx([5.0, 5.2, 5.4])
    assert frames[0].depth.shape == (6, 8) and frames[0].mask is None  # batch size 1, not collated
    assert [float(f.gt_pose[0, 3]) for f in frames] == [0.0, 2.0, 4.0]
    assert list(dm.train_dataloader())[1].index == 2  # re-iterable, no shuffling
