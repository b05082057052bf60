"""Motion-mask providers: where the system learns which pixels move.

Every provider is called once per frame before tracking (``context=None``); providers that need the
tracked pose and the map (``needs_tracked_pose``) are called after tracking instead, with a
:class:`MaskContext`. The mask feeds the pixel sampler and the offset loss.

Providers (config group ``masks``): ``dataset`` (masks shipped with the data; here), ``folder``
(:mod:`tivne.masks.folder`, one PNG per frame, nonzero = dynamic), ``none`` (here), ``maskrcnn``
(:mod:`tivne.masks.maskrcnn`, needs torchvision and a local weights file) and ``geometric``
(:mod:`tivne.masks.geometric`, model-free: the frame against earlier frames, or the map, at the
tracked pose; earlier keyframes' masks are revised as later frames arrive, see ``MaskProvider.revise``).
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
    last_mapped_tau: the latest time the map was trained on (None: the caller does not say).
    """

    field: torch.nn.Module
    pose: torch.Tensor
    K: torch.Tensor
    tau: float
    render: object
    frame_number: int
    last_mapped_tau: float | None = None


class MaskProvider:
    """Base class: returns an (H, W) bool mask (True = dynamic) or None (unknown).

    Providers that need the tracked pose are called after tracking; ``predict`` gives the mask
    tracking should use before that (from earlier frames), or None.
    """

    name = "base"
    needs_tracked_pose = False

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        raise NotImplementedError

    def predict(self, frame: Frame) -> torch.Tensor | None:
        """A mask for ``frame`` before its pose is known (for tracking); None = unknown."""
        return None

    def revise(self, keyframes: list, current, K: torch.Tensor) -> dict[int, torch.Tensor]:
        """The grown masks of earlier keyframes (Views with their poses), from what ``current`` (a
        tracked View) shows about them (a moving object is often only recognisable once it has moved
        away): {frame id: (H, W) bool} of the masks that grew; the caller stores them. Default: masks
        are final."""
        return {}

    def state_dict(self) -> dict:
        """What the provider carries from frame to frame (tensors, numbers, lists; no numpy), for a
        run's checkpoint. Default: nothing (a stateless provider)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict`'s result (a resumed run). Default: nothing to restore."""


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


class RecordingMasks(MaskProvider):
    """Wraps a provider and keeps every mask it returns, with the frame's GT mask and timestamp (per
    frame index) -- for benchmarks: hand it to :func:`tivne.slam.run.run` (``masks=``) and read it after.
    """

    def __init__(self, inner: MaskProvider) -> None:
        self.inner = inner
        self.name = inner.name
        self.needs_tracked_pose = inner.needs_tracked_pose
        self.masks: dict[int, torch.Tensor | None] = {}
        self.gt: dict[int, torch.Tensor | None] = {}
        self.timestamps: dict[int, float] = {}

    def predict(self, frame: Frame) -> torch.Tensor | None:
        return self.inner.predict(frame)

    def revise(self, keyframes: list, current, K: torch.Tensor) -> dict[int, torch.Tensor]:
        return self.inner.revise(keyframes, current, K)

    def state_dict(self) -> dict:
        return self.inner.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.inner.load_state_dict(state)

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        mask = self.inner(frame, context)
        self.masks[frame.index] = None if mask is None else mask.detach().cpu().clone()
        self.gt[frame.index] = None if frame.mask is None else frame.mask.detach().cpu().clone()
        self.timestamps[frame.index] = float(frame.timestamp)
        return mask
