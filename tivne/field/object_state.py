"""An :class:`ObjectField`'s objects as plain tensors (checkpoint ``extra["objects"]``) and back.

The checkpoint's ``field_state`` stays the static field's (every reader loads it as a
:class:`TimeVaryingField`); the object fields, their first times and their tracks (sampled at the
observed times, interpolated on SE(3) in between on load) travel beside it, so ``tivne.mesh``,
``tivne.evaluate`` and the PSNR re-render see the objects too.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from data_modules.poses import pose_on_track
from tivne.config import FieldConfig
from tivne.field.networks import TimeVaryingField
from tivne.field.objects import ObjectField, ObjectPoses, ObjectSlot


class RecordedTrack:
    """A track rebuilt from its samples: (N,) τ increasing, (N, 4, 4) object-to-world, box (2, 3)
    or None. Between samples SLERP + lerp of the box's middle; outside them the end pose continued at
    the end's velocity, as the live track (:func:`data_modules.poses.pose_on_track`)."""

    def __init__(self, taus: torch.Tensor, poses: torch.Tensor, box: torch.Tensor | None) -> None:
        self.taus = np.asarray(torch.as_tensor(taus, dtype=torch.float64))
        self.poses = torch.as_tensor(poses, dtype=torch.float64)
        self.box = None if box is None else torch.as_tensor(box, dtype=torch.float64)

    def pose_at(self, tau: float) -> torch.Tensor:
        return pose_on_track(self.taus, self.poses, float(tau), pivot=None if self.box is None else self.box.mean(0))

    def observed_taus(self) -> list[float]:
        return [float(t) for t in self.taus]

    def observed_near(self, tau: float, window: float) -> bool:
        return bool(len(self.taus)) and bool(np.abs(self.taus - float(tau)).min() <= window)


def track_samples(track: ObjectPoses, taus: list[float] = ()) -> dict[str, Any]:
    """A track's poses at the τ it was observed (``observed_taus()`` when it has them, else ``taus``)."""
    own = getattr(track, "observed_taus", None)
    at = sorted(set(own() if own is not None else taus))
    poses = torch.stack([track.pose_at(t) for t in at]) if at else torch.zeros(0, 4, 4, dtype=torch.float64)
    return {"taus": torch.tensor(at, dtype=torch.float64), "poses": poses, "box": None if track.box is None else track.box.clone()}


def objects_payload(field: TimeVaryingField, taus: list[float] = ()) -> dict[str, Any]:
    """``{"objects": ...}`` for a checkpoint's ``extra`` ({} for a field without objects).

    Args:
        taus: the processed frames' field times (where a track without its own record is sampled).
    """
    if not isinstance(field, ObjectField):
        return {}
    slots = {
        str(i): {"tau0": s.tau0, "state": {k: v.detach().cpu() for k, v in s.field.state_dict().items()}}
        for i, s in field.slots.items()
    }
    tracks = {str(i): track_samples(t, taus) for i, t in field.tracks.items()}
    settings = {"box_margin": field.box_margin, "window": field.window, "mesh_resolution": field.mesh_resolution}
    settings["object_dilation"] = field.object_dilation
    return {"objects": {"object_config": dataclasses.asdict(field.object_cfg), "settings": settings, "slots": slots, "tracks": tracks}}


def restore_objects(field: TimeVaryingField, extra: dict[str, Any] | None) -> TimeVaryingField:
    """The static ``field`` as loaded, or (``extra`` holds objects) an :class:`ObjectField` with its
    state and the saved objects. Raises KeyError / TypeError / RuntimeError on another version's payload."""
    saved = (extra or {}).get("objects")
    if not saved:
        return field
    state = field.state_dict()
    object_cfg = FieldConfig.from_mapping(saved["object_config"])
    out = ObjectField(object_cfg, **saved["settings"], cfg=field.cfg)
    out.grid.load_sparse_state(grid_state(state))
    out.load_state_dict(state)
    out.set_tracks({int(i): RecordedTrack(t["taus"], t["poses"], t["box"]) for i, t in saved["tracks"].items()})
    for i, slot in saved["slots"].items():
        obj = TimeVaryingField(object_cfg)
        obj.grid.load_sparse_state(grid_state(slot["state"]))
        obj.load_state_dict(slot["state"])
        out.slots[int(i)] = ObjectSlot(obj.to(field.grid.voxel_keys.device), float(slot["tau0"]))
    return out.to(field.grid.voxel_keys.device)


def grid_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The ``grid.*`` entries of a field's state dict, without the prefix."""
    return {k[len("grid."):]: v for k, v in state.items() if k.startswith("grid.")}


def load_objects_into(field: TimeVaryingField, extra: dict[str, Any] | None) -> None:
    """Resume: give a freshly built :class:`ObjectField` (its tracks already set, its optimiser
    bound) the saved object fields, created in their saved order so the optimiser's parameter
    groups line up with the saved optimiser state. A no-op for other fields or without objects."""
    saved = (extra or {}).get("objects")
    if not saved or not isinstance(field, ObjectField):
        return
    for i, slot in saved["slots"].items():
        live = field._slot(int(i), float(slot["tau0"])).field
        state = {k: v.to(field.grid.voxel_keys.device) for k, v in slot["state"].items()}
        live.grid.load_sparse_state(grid_state(state))
        live.load_state_dict(state)
