"""What the object tracker keeps of each object between frames: observations waiting for a whole view
(:class:`PendingView`) and the tracking state of a followed object (:class:`LiveObject`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from tivne.slam.objects.references import Reference
from tivne.slam.tracking.pyramid import PyramidLevel


@dataclass
class PendingView:
    """A new object's observation while the image border cuts it off (before its track starts)."""

    pyramid: list[PyramidLevel]
    mask: torch.Tensor
    T_wc: torch.Tensor
    tau: float
    time: float
    pixels: int


@dataclass
class LiveObject:
    """Per-object tracking state: its keyframe observations (oldest first, at most the tracker's
    ``MAX_REFERENCES``), the last observation's object-frame points (M, 3), their size (m) and time (s)."""

    references: list[Reference]
    points: torch.Tensor
    size: float
    last_time: float
    rms: list[float] = field(default_factory=list)  # photometric RMS of its last alignments

    @property
    def reference(self) -> Reference | None:
        return self.references[-1] if self.references else None

    def typical_rms(self) -> float:
        """The median photometric RMS of the object's recent alignments (nan before any)."""
        return float(np.median(self.rms)) if self.rms else float("nan")
