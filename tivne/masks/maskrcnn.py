"""Mask R-CNN motion masks (the paper's source): torchvision ``maskrcnn_resnet50_fpn`` from a local file.

torchvision is an optional extra (``pip install 'tivne[detect]'``) imported only when the provider is
built; nothing is ever downloaded (``weights=None, weights_backbone=None``). The post-processing
(:func:`detections_to_mask`) and the model-running code take any callable with torchvision's output
format, so they are tested without torchvision.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from data_modules.frame import DatasetError, Frame
from tivne.masks.base import MaskContext, MaskProvider
from tivne.masks.settings import MaskRCNNConfig
from tivne.morphology import dilate

COCO_DYNAMIC = (1, 2, 3, 4, 6, 8, 16, 17, 18, 19, 88)  # person … dog, horse, teddy bear
INSTALL_HINT = "maskrcnn needs torchvision: pip install 'tivne[detect]'"


class MaskRCNNError(DatasetError):
    """One-line configuration/installation error of the maskrcnn provider."""


def detections_to_mask(
    detections: dict[str, torch.Tensor],
    size: tuple[int, int],
    classes: Sequence[int],
    score_threshold: float = 0.5,
    mask_threshold: float = 0.5,
) -> torch.Tensor:
    """Union of the instance masks of dynamic classes, at ``size``.

    Args:
        detections: torchvision output for one image: boxes (N, 4), labels (N,), scores (N,),
            masks (N, 1, h, w) soft masks in [0, 1] at the network input size.
        size: (H, W) of the frame.
    Returns:
        (H, W) bool.
    """
    labels = detections["labels"].reshape(-1)
    scores = detections["scores"].reshape(-1)
    masks = detections["masks"]
    keep = (scores >= score_threshold) & torch.isin(labels, torch.as_tensor(list(classes), dtype=labels.dtype, device=labels.device))
    if masks.numel() == 0 or not bool(keep.any()):
        return torch.zeros(size, dtype=torch.bool, device=masks.device)
    soft = masks[keep].float()
    if soft.ndim == 3:
        soft = soft[:, None]
    if tuple(soft.shape[-2:]) != tuple(size):
        soft = F.interpolate(soft, size=size, mode="bilinear", align_corners=False)
    return (soft[:, 0] > mask_threshold).any(dim=0)


def load_maskrcnn(weights: str | Path, num_classes: int = 91) -> torch.nn.Module:
    """Build ``maskrcnn_resnet50_fpn`` without downloading and load the state dict at ``weights``."""
    path = Path(str(weights)).expanduser()
    if not path.is_file():
        raise MaskRCNNError("masks.weights", f"{path}: file not found")
    try:
        from torchvision.models.detection import maskrcnn_resnet50_fpn
    except Exception as exc:  # ImportError, or a torchvision built for another torch
        raise MaskRCNNError("masks.provider", f"{INSTALL_HINT} ({type(exc).__name__}: {exc})") from None
    model = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=num_classes)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
            state = state["model"]
        model.load_state_dict(state)
    except Exception as exc:
        raise MaskRCNNError("masks.weights", f"{path}: not a maskrcnn_resnet50_fpn state dict ({type(exc).__name__})") from None
    return model.eval()


class MaskRCNNMasks(MaskProvider):
    """Instance masks of configurable COCO classes (``classes``) as the motion mask.

    The frame is resized so its longest side is ``input_size`` (None = as is) before inference;
    masks come back at the frame size. ``model`` injects any callable with torchvision's interface
    (list of (3, h, w) images -> list of dicts), e.g. a fake in tests; otherwise ``weights`` is loaded.
    """

    name = "maskrcnn"

    def __init__(self, model: Callable[[list[torch.Tensor]], list[dict[str, Any]]] | None = None, **settings: Any) -> None:
        """``settings``: :class:`tivne.masks.settings.MaskRCNNConfig` keys (checked there); ``model``:
        a detector to use instead of loading ``weights`` (tests)."""
        cfg = MaskRCNNConfig(**settings)
        weights, classes, score_threshold, mask_threshold = cfg.weights, cfg.classes, cfg.score_threshold, cfg.mask_threshold
        input_size, dilate, device = cfg.input_size, cfg.dilate, cfg.device
        if model is None:
            if weights is None:
                raise MaskRCNNError("masks.weights", "a weights file is required (masks.provider.weights=PATH)")
            model = load_maskrcnn(weights)
        self.model = model
        self.classes = tuple(int(c) for c in classes)
        self.score_threshold = float(score_threshold)
        self.mask_threshold = float(mask_threshold)
        self.input_size = None if input_size is None else int(input_size)
        self.dilate = int(dilate)
        self.device = device
        if device is not None and isinstance(model, torch.nn.Module):
            model.to(device)

    @torch.no_grad()
    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        h, w = frame.height, frame.width
        device = self.device or frame.rgb.device
        image = frame.rgb.to(device).permute(2, 0, 1).float()  # (3, H, W) in [0, 1]
        if self.input_size is not None and max(h, w) != self.input_size:
            scale = self.input_size / max(h, w)
            size = (max(int(round(h * scale)), 1), max(int(round(w * scale)), 1))
            image = F.interpolate(image[None], size=size, mode="bilinear", align_corners=False)[0]
        detections = self.model([image])[0]
        mask = detections_to_mask(detections, (h, w), self.classes, self.score_threshold, self.mask_threshold)
        mask = dilate(mask, self.dilate)
        return mask.to(frame.depth.device)
