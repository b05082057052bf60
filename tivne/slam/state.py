"""What the loop hands out: one :class:`FrameReport` per frame (typed; scalars are made only for
logging), and the run's time accounting."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field

import torch

from tivne.render.rays import View
from tivne.slam.backend.apply import Correction
from tivne.slam.mapping import MapRound
from tivne.slam.objects.tracker import ObjectObservation
from tivne.slam.tracking import TrackResult


@dataclass
class Timers:
    """Where the run's time went (seconds), for metrics.json: each frame's and the final pass."""

    per_frame: list[float] = dc_field(default_factory=list)
    refine_s: float = 0.0


@dataclass(frozen=True)
class FrameReport:
    """One processed frame: its stream index, timestamp (s) and field time τ; the tracking result;
    whether it became a keyframe and the odometry reference; the mapping round it ran (None: not
    mapped); the view as mapped (its pose and final mask); seconds spent; the map's size after it;
    what the object tracker made of each moving object (empty without ``objects.track``); what the
    pose graph's correction did at a new keyframe (None without ``backend.method=graph``)."""

    index: int
    timestamp: float
    tau: float
    track: TrackResult
    view: View
    keyframe: bool
    new_reference: bool
    mapping: MapRound | None
    seconds: float
    voxels: int
    objects: tuple[ObjectObservation, ...] = ()
    correction: Correction | None = None

    @property
    def pose(self) -> torch.Tensor:
        """(4, 4) c2w pose the frame was recorded with."""
        return self.view.pose

    def scalars(self) -> dict[str, float]:
        """Every per-frame scalar, by its TensorBoard name (``track/*``, ``map/*``, ``perf/*``)."""
        out = {f"track/{k}": v for k, v in self.track.scalars().items()}
        out["track/new_reference"] = float(self.new_reference)
        if self.mapping is not None:
            out |= {f"map/{k}": v for k, v in self.mapping.scalars().items()}
        if self.objects:
            out["objects/observed"] = float(len(self.objects))
        if self.correction is not None:
            out |= {"graph/moved": float(len(self.correction.moved)), "graph/displacement_m": self.correction.max_displacement_m}
        return out | {"perf/s_per_frame": self.seconds, "map/voxels": float(self.voxels)}
