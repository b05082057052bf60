"""Ground-truth object tracks (an ORACLE): the dataset's exact object poses, in the SLAM frame, in
the shape of the tracks the object fields read (:class:`tivne.field.objects.ObjectPoses`).

``field=objects`` runs on the object tracker's poses (``object_field.tracks=tracked``); these are
the upper bound of the ablation (``object_field.tracks=oracle``), and every figure measured with
them says so. The SLAM frame is the first processed camera's, so a world pose
maps into it by the inverse of that camera's GT pose (the evaluation maps meshes back the same way).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from tivne.config import ConfigError, ObjectFieldConfig
from tivne.field.networks import TimeVaryingField
from tivne.field.objects import ObjectField


@dataclass
class GroundTruthTrack:
    """One object's exact motion. ``world_pose(t)``: (4, 4) object-to-world at sequence time t
    seconds; ``slam_from_world``: (4, 4); τ = (t - t0)·time_scale; ``taus``: the processed frames'
    field times (the object counts as observed at each); ``box``: (2, 3) [min, max] object frame."""

    world_pose: Callable[[float], torch.Tensor]
    slam_from_world: torch.Tensor
    t0: float
    time_scale: float
    taus: np.ndarray
    box: torch.Tensor | None

    def pose_at(self, tau: float) -> torch.Tensor:
        """(4, 4) float64 object-to-SLAM-frame pose at field time τ (exact, any τ)."""
        t = self.t0 + float(tau) / self.time_scale
        return self.slam_from_world @ torch.as_tensor(self.world_pose(t), dtype=torch.float64)

    def observed_taus(self) -> list[float]:
        return [float(t) for t in self.taus]

    def observed_near(self, tau: float, window: float) -> bool:
        return bool(len(self.taus)) and bool(np.abs(self.taus - float(tau)).min() <= window)


def ground_truth_tracks(view: Any, time_scale: float) -> dict[int, GroundTruthTrack]:
    """{object id (1-based, the dataset's label order): track} of every moving object of ``view``
    (a :class:`data_modules.sequence.SequenceView` of a dataset with ``object_poses`` and
    ``dynamic_box``, e.g. the synthetic family).

    Raises:
        ConfigError: the dataset has no ground-truth object poses.
    """
    base = getattr(view, "base", view)
    if not (hasattr(base, "object_poses") and hasattr(base, "dynamic_box") and hasattr(base, "camera_pose")):
        raise ConfigError(
            f"objects.tracks=oracle: dataset {getattr(view, 'name', '?')!r} has no ground-truth object poses "
            "(the synthetic family has them); object_field.tracks=tracked estimates them"
        )
    first = int(getattr(view, "source_indices", [0])[0])
    slam_from_world = torch.linalg.inv(torch.as_tensor(base.camera_pose(first), dtype=torch.float64))
    stamps = np.asarray(view.timestamps, dtype=np.float64)
    t0 = float(stamps[0])
    taus = (stamps - t0) * float(time_scale)
    tracks = {}
    for k, name in enumerate(base.object_names, start=1):
        _, half, _ = base.dynamic_box(t0, name)
        half = torch.as_tensor(half, dtype=torch.float64)
        tracks[k] = GroundTruthTrack(lambda t, n=name: base.object_poses(t)[n], slam_from_world, t0, float(time_scale), taus,
                                     torch.stack([-half, half]))
    return tracks


def attach_tracks(field: TimeVaryingField, view: Any, cfg: ObjectFieldConfig,
                  tracked: Callable[[], Mapping[int, Any]] | None = None) -> None:
    """Give an :class:`ObjectField` the tracks ``cfg.tracks`` names: "oracle", the GT of ``view``;
    "tracked", what ``tracked()`` returns (the run's object tracker; the run's settings refuse
    "tracked" without one). A no-op for other fields.

    Raises:
        ConfigError: "oracle" on a dataset without GT object poses.
    """
    if not isinstance(field, ObjectField):
        return
    if cfg.tracks == "oracle":
        field.set_tracks(ground_truth_tracks(view, field.time_scale))
    elif tracked is not None:
        field.set_tracks(tracked)
