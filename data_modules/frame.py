"""The data contract every dataset reader produces: camera intrinsics and one RGB-D frame."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch


class DatasetError(ValueError):
    """Bad input data. The message is one line: ``<file or field>: <what is wrong>``."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``; ``readout_s``: a rolling
    shutter's readout, the seconds from the first row to the last (0 = a global shutter)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    readout_s: float = 0.0

    def __post_init__(self) -> None:
        """Refuse values no camera has; build through :func:`intrinsics_from` to name the source."""
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise DatasetError("intrinsics", f"{name} must be finite, got {value}")
        if self.fx <= 0 or self.fy <= 0:
            raise DatasetError("intrinsics", f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise DatasetError("intrinsics", f"image size must be positive, got {self.width}x{self.height}")
        if not 0.0 <= self.readout_s < 1.0:  # not a frame rate's worth of seconds
            raise DatasetError("intrinsics", f"readout_s must be in [0, 1) seconds, got {self.readout_s}")
        # Pixel centres are at integer coordinates, so the image spans [-0.5, W - 0.5] x [-0.5, H - 0.5].
        # A principal point outside it (e.g. 640x480 intrinsics on a smaller image) tracks nothing useful.
        if not (-0.5 <= self.cx <= self.width - 0.5 and -0.5 <= self.cy <= self.height - 0.5):
            raise DatasetError(
                "intrinsics",
                f"principal point (cx={self.cx:g}, cy={self.cy:g}) is outside the {self.width}x{self.height} image"
                " (intrinsics for another image size?)",
            )

    def K(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        """The 3x3 camera matrix."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device
        )

    def resized(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics of the same camera after resizing the image to ``width`` x ``height``.

        Uses the pixel-corner convention (pixel centres at integer + 0.5 in continuous coordinates),
        so a principal point at the image centre stays at the image centre.
        """
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=width,
            height=height,
            readout_s=self.readout_s,  # the same rows, read over the same time
        )

    def as_dict(self) -> dict[str, float | int]:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height,
                "readout_s": self.readout_s}


def intrinsics_from(source: str | Path, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                    readout_s: float = 0.0) -> Intrinsics:
    """:class:`Intrinsics` built from values read from ``source``; a bad value raises a one-line
    :class:`DatasetError` naming ``source`` (a file, or a config key such as ``dataset.intrinsics``)."""
    try:
        values = float(fx), float(fy), float(cx), float(cy), int(width), int(height), float(readout_s)
    except (TypeError, ValueError):
        raise DatasetError(source, f"fx, fy, cx, cy, width, height, readout_s must be numbers, got {fx}, {fy}, {cx}, {cy}, {width}, "
                                   f"{height}, {readout_s}") from None
    try:
        return Intrinsics(*values)
    except DatasetError as e:
        raise DatasetError(source, e.problem) from None


@dataclass
class Frame:
    """One RGB-D frame.

    Attributes:
        index: position of the frame in the original recording (before stride).
        timestamp: seconds; strictly increasing along a sequence.
        rgb: (H, W, 3) float32 in [0, 1].
        depth: (H, W) float32 metres, 0 = invalid.
        mask: (H, W) bool, True = dynamic pixel, or None when the dataset has no masks.
        gt_pose: (4, 4) float64 camera-to-world, or None.
        source: file name of the colour image the frame was read from (e.g. ``rgb_0042.png``; what
            per-frame side files such as mask PNGs are matched by), or None for frames without a
            file of their own (KLG logs, synthetic sequences).
        instances: (H, W) int64 object instance id per pixel (0 = static, k > 0 = the dataset's
            object k, the same k in every frame), or None when the dataset has no instance masks.
    """

    index: int
    timestamp: float
    rgb: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor | None = None
    gt_pose: torch.Tensor | None = None
    source: str | None = None
    instances: torch.Tensor | None = None

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    def to(self, device: torch.device | str) -> "Frame":
        return replace(
            self,
            rgb=self.rgb.to(device),
            depth=self.depth.to(device),
            mask=None if self.mask is None else self.mask.to(device),
            gt_pose=None if self.gt_pose is None else self.gt_pose.to(device),
            instances=None if self.instances is None else self.instances.to(device),
        )

    def validate(self, source: str | Path, intrinsics: Intrinsics | None = None) -> "Frame":
        """Check shapes, dtypes and values; raise :class:`DatasetError` naming ``source`` if wrong.

        NaN / inf depth is an error here: readers that know their format's "invalid" encoding must
        map it to 0 before building the frame.
        """
        if self.depth.ndim != 2:
            raise DatasetError(source, f"depth must be (H, W), got shape {tuple(self.depth.shape)}")
        h, w = self.depth.shape
        if tuple(self.rgb.shape) != (h, w, 3):
            raise DatasetError(source, f"rgb shape {tuple(self.rgb.shape)} does not match depth shape {(h, w)} (+3 channels)")
        if intrinsics is not None and (w, h) != (intrinsics.width, intrinsics.height):
            raise DatasetError(source, f"image is {w}x{h} but the intrinsics are for {intrinsics.width}x{intrinsics.height}")
        if self.rgb.dtype != torch.float32 or self.depth.dtype != torch.float32:
            raise DatasetError(source, f"rgb/depth must be float32, got {self.rgb.dtype}/{self.depth.dtype}")
        if not torch.isfinite(self.depth).all():
            raise DatasetError(source, "depth contains NaN or inf values")
        if (self.depth < 0).any():
            raise DatasetError(source, f"depth contains negative values (min {float(self.depth.min()):.3f} m)")
        if not torch.isfinite(self.rgb).all() or self.rgb.min() < 0 or self.rgb.max() > 1:
            raise DatasetError(source, "rgb must be finite and within [0, 1]")
        if self.mask is not None:
            if self.mask.dtype != torch.bool or tuple(self.mask.shape) != (h, w):
                raise DatasetError(source, f"mask must be bool (H, W)={(h, w)}, got {self.mask.dtype} {tuple(self.mask.shape)}")
        if self.instances is not None:
            if self.instances.dtype != torch.int64 or tuple(self.instances.shape) != (h, w):
                raise DatasetError(source, f"instances must be int64 (H, W)={(h, w)}, got {self.instances.dtype} {tuple(self.instances.shape)}")
            if bool((self.instances < 0).any()):
                raise DatasetError(source, "instance ids must be >= 0 (0 = static)")
        if self.gt_pose is not None:
            if tuple(self.gt_pose.shape) != (4, 4) or not torch.isfinite(self.gt_pose).all():
                raise DatasetError(source, "gt_pose must be a finite 4x4 matrix")
        if not math.isfinite(self.timestamp):
            raise DatasetError(source, f"timestamp must be finite, got {self.timestamp}")
        return self
