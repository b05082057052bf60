"""Sequence datasets and the one LightningDataModule that wraps any of them."""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import replace

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset, Subset

from data_modules.frame import DatasetError, Frame, Intrinsics


class SequenceDataset(Dataset, abc.ABC):
    """A recorded RGB-D sequence: ``len(ds)`` frames in time order, ``ds[i]`` is a :class:`Frame`.

    Subclasses set ``name``, ``intrinsics`` and ``timestamps`` (strictly increasing seconds, one per frame)
    in ``__init__`` and implement :meth:`load_frame`.
    """

    name: str
    intrinsics: Intrinsics
    timestamps: np.ndarray
    has_gt_poses: bool = False
    has_masks: bool = False

    def __len__(self) -> int:
        return len(self.timestamps)

    @abc.abstractmethod
    def load_frame(self, i: int) -> Frame:
        """Read frame ``i`` (0 <= i < len) from disk or generate it."""

    def camera_pose(self, i: int) -> torch.Tensor:
        """GT camera-to-world pose (4, 4) float64 of frame ``i`` without reading images.

        Readers with ground truth keep ``gt_poses``: one (4, 4) tensor per frame, or None where the
        ground truth does not cover the frame.
        """
        poses = getattr(self, "gt_poses", None)
        if poses is None or poses[i] is None:
            raise DatasetError(f"{self.name}: frame {i}", "has no ground-truth pose (outside the GT coverage)")
        return poses[i].clone()

    def __getitem__(self, i: int) -> Frame:
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range for {self.name} with {len(self)} frames")
        return self.load_frame(i)

    def describe(self) -> dict[str, object]:
        """Static facts about the sequence (no frame is read)."""
        duration = float(self.timestamps[-1] - self.timestamps[0]) if len(self) else 0.0
        return {
            "name": self.name,
            "frames": len(self),
            "duration_s": duration,
            "width": self.intrinsics.width,
            "height": self.intrinsics.height,
            "intrinsics": self.intrinsics.as_dict(),
            "has_gt_poses": bool(self.has_gt_poses),
            "has_masks": bool(self.has_masks),
        }


def _is_integer(value: object) -> bool:
    """An integer (not a bool, not 1.5)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _is_count(value: object, least: int = 1) -> bool:
    """An integer >= ``least`` (1: a count; 0: a frame number)."""
    return _is_integer(value) and value >= least


def _is_frame_range(value: object) -> bool:
    """[first, last] frame numbers with first <= last."""
    return not isinstance(value, (str, bytes)) and len(value) == 2 and all(_is_count(v, 0) for v in value) and value[0] <= value[1]


def _count_rule(value: object) -> str:
    """The rule a bad count broke: ">= 1" for an integer below it, "an integer >= 1" otherwise."""
    return ">= 1" if _is_integer(value) else "an integer >= 1"


def resize_frame(frame: Frame, width: int, height: int) -> Frame:
    """Resize a frame: area-averaged colour, nearest-neighbour depth, mask and instance ids (no mixed
    depths or ids at edges)."""
    if (frame.width, frame.height) == (width, height):
        return frame
    rgb = F.interpolate(frame.rgb.permute(2, 0, 1)[None], size=(height, width), mode="area")[0].permute(1, 2, 0)
    depth = F.interpolate(frame.depth[None, None], size=(height, width), mode="nearest-exact")[0, 0]
    mask = None
    if frame.mask is not None:
        mask = F.interpolate(frame.mask[None, None].float(), size=(height, width), mode="nearest-exact")[0, 0] > 0.5
    instances = None
    if frame.instances is not None:  # ids up to 2^24 are exact in float32
        instances = F.interpolate(frame.instances[None, None].float(), size=(height, width), mode="nearest-exact")[0, 0].long()
    return replace(frame, rgb=rgb.contiguous().clamp(0, 1), depth=depth.contiguous(), mask=mask, instances=instances)


class SequenceView(SequenceDataset):
    """A strided, truncated, resized and depth-clipped view of another sequence, from its
    ``first_frame``-th frame on (0-based, before the stride: a stretch of a long recording), without
    the recording's frames ``drop_frames`` = [first, last] (a dropped stretch, as a recorder that
    stalled leaves one)."""

    def __init__(
        self,
        base: SequenceDataset,
        stride: int = 1,
        max_frames: int | None = None,
        resize: Sequence[int] | None = None,
        depth_min: float = 0.0,
        depth_max: float | None = None,
        first_frame: int = 0,
        drop_frames: Sequence[int] | None = None,
    ) -> None:
        if not _is_count(stride):
            raise DatasetError("data.stride", f"must be {_count_rule(stride)}, got {stride!r}")
        if max_frames is not None and not _is_count(max_frames):
            raise DatasetError("data.max_frames", f"must be {_count_rule(max_frames)} or null, got {max_frames!r}")
        for key, value in (("depth_min", depth_min), ("depth_max", 1.0 if depth_max is None else depth_max)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
                raise DatasetError(f"data.{key}", f"must be a finite number >= 0, got {value!r}")
        if depth_max is not None and depth_max <= depth_min:
            raise DatasetError("data.depth_max", f"must exceed depth_min={depth_min}, got {depth_max}")
        if not _is_count(first_frame, 0):
            raise DatasetError("data.first_frame", f"must be an integer >= 0, got {first_frame!r}")
        if first_frame >= len(base):
            raise DatasetError("data.first_frame", f"must be below the sequence's {len(base)} frames, got {first_frame}")
        self.base = base
        self.name = base.name
        indices = np.arange(first_frame, len(base), stride)
        if drop_frames is not None:
            if not _is_frame_range(drop_frames):
                raise DatasetError("data.drop_frames", f"must be [first, last] frame numbers, first <= last, got {list(drop_frames)}")
            indices = indices[(indices < drop_frames[0]) | (indices > drop_frames[1])]
            if len(indices) == 0:
                raise DatasetError("data.drop_frames", f"{list(drop_frames)} leaves none of the {len(base)} frames")
        self.source_indices = indices[:max_frames]
        self.timestamps = np.asarray(base.timestamps)[self.source_indices]
        self.has_gt_poses = base.has_gt_poses
        self.has_masks = base.has_masks
        if resize is not None:
            if isinstance(resize, (str, bytes)) or len(resize) != 2 or not all(_is_count(v) for v in resize):
                raise DatasetError("data.resize", f"must be [width, height], got {list(resize)}")
            self.size = (int(resize[0]), int(resize[1]))
            self.intrinsics = base.intrinsics.resized(*self.size)
        else:
            self.size = None
            self.intrinsics = base.intrinsics
        self.depth_min = depth_min
        self.depth_max = depth_max

    def load_frame(self, i: int) -> Frame:
        frame = self.base[int(self.source_indices[i])]
        if self.size is not None:
            frame = resize_frame(frame, *self.size)
        depth = frame.depth
        invalid = depth < self.depth_min
        if self.depth_max is not None:
            invalid |= depth > self.depth_max
        if invalid.any():
            frame = replace(frame, depth=torch.where(invalid, torch.zeros_like(depth), depth))
        return frame


def _first(batch: list[Frame]) -> Frame:
    return batch[0]


class SequenceDataModule(L.LightningDataModule):
    """Streams one sequence frame by frame (batch size 1, time order, no shuffling), from frame
    ``start`` of the view on (a resumed run skips the frames it has processed)."""

    def __init__(
        self,
        dataset: SequenceDataset,
        stride: int = 1,
        max_frames: int | None = None,
        resize: Sequence[int] | None = None,
        depth_min: float = 0.0,
        depth_max: float | None = None,
        num_workers: int = 0,
        start: int = 0,
        first_frame: int = 0,
        drop_frames: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        self.view = SequenceView(dataset, stride, max_frames, resize, depth_min, depth_max, first_frame, drop_frames)
        self.num_workers = num_workers
        self.start = int(start)

    @property
    def intrinsics(self) -> Intrinsics:
        return self.view.intrinsics

    def train_dataloader(self) -> DataLoader:
        if not 0 <= self.start <= len(self.view):
            raise DatasetError("start", f"frame {self.start} is outside the sequence's {len(self.view)} frames")
        frames = self.view if self.start == 0 else Subset(self.view, range(self.start, len(self.view)))
        return DataLoader(
            frames,
            batch_size=1,
            shuffle=False,
            num_workers=self.num_workers,
            collate_fn=_first,
            persistent_workers=self.num_workers > 0,
        )
