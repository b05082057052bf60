"""Mask R-CNN provider: post-processing with a fake model, clear errors, and (with torchvision) end to end."""

from __future__ import annotations

import builtins
import sys

import pytest
import torch

from data_modules.frame import Frame
from tivne.masks.maskrcnn import (
    INSTALL_HINT,
    MaskRCNNError,
    MaskRCNNMasks,
    detections_to_mask,
    load_maskrcnn,
)

H, W = 30, 40


def frame() -> Frame:
    return Frame(index=0, timestamp=0.0, rgb=torch.rand(H, W, 3), depth=torch.ones(H, W))


def soft_box(h: int, w: int, y0: int, y1: int, x0: int, x1: int, value: float = 0.9) -> torch.Tensor:
    m = torch.zeros(1, h, w)
    m[:, y0:y1, x0:x1] = value
    return m


def fake_output(h: int, w: int) -> dict[str, torch.Tensor]:
    """torchvision's per-image dict: a person, a chair (static class), a low-score car, a weak teddy."""
    masks = torch.stack([
        soft_box(h, w, 0, h // 2, 0, w // 2),  # person, confident
        soft_box(h, w, h // 2, h, w // 2, w),  # chair (62): not dynamic
        soft_box(h, w, h // 2, h, 0, w // 2),  # car with a low score
        soft_box(h, w, 0, h // 2, w // 2, w, value=0.3),  # teddy bear with a faint mask
    ])
    return {
        "boxes": torch.zeros(4, 4),
        "labels": torch.tensor([1, 62, 3, 88]),
        "scores": torch.tensor([0.9, 0.95, 0.2, 0.8]),
        "masks": masks,
    }


def test_detections_to_mask_filters_thresholds_and_unions():
    out = fake_output(H, W)
    mask = detections_to_mask(out, (H, W), classes=(1, 3, 88), score_threshold=0.5, mask_threshold=0.5)
    expected = torch.zeros(H, W, dtype=torch.bool)
    expected[: H // 2, : W // 2] = True  # only the person survives
    assert torch.equal(mask, expected)
    low = detections_to_mask(out, (H, W), classes=(1, 3, 88), score_threshold=0.1, mask_threshold=0.25)
    assert low[H - 1, 0] and low[0, W - 1] and not low[H - 1, W - 1]  # car + teddy join the union; chair never
    empty = {k: v[:0] for k, v in out.items()}
    assert not detections_to_mask(empty, (H, W), (1,)).any()


def test_masks_resized_back_to_the_frame():
    out = fake_output(15, 20)  # the network ran at half size
    mask = detections_to_mask(out, (H, W), classes=(1,))
    assert mask.shape == (H, W) and mask[: H // 2 - 1, : W // 2 - 1].all() and not mask[H // 2 + 1 :].any()


def test_provider_runs_a_fake_model_at_the_input_size():
    seen = []

    def model(images):
        seen.append(tuple(images[0].shape))
        _, h, w = images[0].shape
        return [fake_output(h, w)]

    provider = MaskRCNNMasks(model=model, classes=(1,), input_size=20)
    mask = provider(frame(), None)
    assert seen == [(3, 15, 20)]  # longest side resized to input_size
    assert mask.dtype == torch.bool and mask.shape == (H, W) and mask[: H // 2 - 2, : W // 2 - 1].all()
    assert not mask[H // 2 :].any() and not mask[:, W // 2 :].any()  # the chair's quadrant stays static
    dilated = MaskRCNNMasks(model=model, classes=(1,), input_size=None, dilate=1)(frame(), None)
    assert seen[-1] == (3, H, W) and dilated.sum() > mask.sum()
    assert not MaskRCNNMasks.needs_tracked_pose


def test_missing_weights_file_is_one_clear_line(tmp_path):
    with pytest.raises(MaskRCNNError, match=r"^masks.weights: .*nope\.pth: file not found$"):
        MaskRCNNMasks(weights=str(tmp_path / "nope.pth"))
    with pytest.raises(MaskRCNNError, match="weights file is required"):
        MaskRCNNMasks(weights=None)


def test_missing_torchvision_is_one_clear_line(tmp_path, monkeypatch):
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"x")
    real_import = builtins.__import__

    def no_torchvision(name, *args, **kwargs):
        if name == "torchvision" or name.startswith("torchvision."):
            raise ImportError("No module named 'torchvision'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_torchvision)
    for mod in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
        monkeypatch.delitem(sys.modules, mod)
    with pytest.raises(MaskRCNNError) as info:
        load_maskrcnn(weights)
    msg = str(info.value)
    assert INSTALL_HINT in msg and "\n" not in msg


def test_maskrcnn_end_to_end_with_random_weights(tmp_path):
    tv = pytest.importorskip("torchvision", reason="torchvision not installed (optional extra: tivne[detect])")
    from torchvision.models.detection import maskrcnn_resnet50_fpn

    torch.manual_seed(0)
    model = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=91)
    path = tmp_path / "maskrcnn_random.pth"
    torch.save(model.state_dict(), path)
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a state dict")
    with pytest.raises(MaskRCNNError, match="bad.pth: not a maskrcnn_resnet50_fpn state dict"):
        load_maskrcnn(bad)
    provider = MaskRCNNMasks(weights=str(path), classes=(1, 3, 88), score_threshold=0.0, input_size=64)
    mask = provider(frame(), None)
    assert mask.dtype == torch.bool and mask.shape == (H, W)
    from tivne.make_masks import make_masks

    class View:
        intrinsics = type("I", (), {"width": W, "height": H})()

        def __len__(self):
            return 2

        def __getitem__(self, i):
            return frame()

    assert make_masks(provider, View(), tmp_path / "out", progress=False)["written"] == 1  # both frames are index 0
    assert tv is not None
