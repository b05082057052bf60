"""Motion-mask providers: where the system learns which pixels move.

Every provider is called once per frame before tracking (``context=None``); providers that need the
tracked pose and the map (``needs_tracked_pose``) are called after tracking instead, with a
:class:`MaskContext`. The mask feeds the pixel sampler and the offset loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from data_modules.frame import Frame


@dataclass
class MaskContext:
    """What the map knows when a post-tracking provider runs.

    field: the TimeVaryingField (frozen for this call). pose: (4, 4) tracked c2w. K: (3, 3).
    tau: the frame's normalised time. render: the RenderConfig. frame_number: position in the stream.
    """

    field: torch.nn.Module
    pose: torch.Tensor
    K: torch.Tensor
    tau: float
    render: object
    frame_number: int


class MaskProvider:
    """Base class: returns an (H, W) bool mask (True = dynamic) or None (unknown)."""

    name = "base"
    needs_tracked_pose = False

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        raise NotImplementedError


class NoMasks(MaskProvider):
    """No motion masks: uniform sampling, no offset loss."""

    name = "none"

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        return None


class DatasetMasks(MaskProvider):
    """Masks shipped with the data (ground truth on the moving cube). Frames without one give None."""

    name = "dataset"

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        return frame.mask
