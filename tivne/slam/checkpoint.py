"""Saving and loading a finished (or interrupted) run: the field, its construction arguments and the trajectory."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from data_modules.frame import DatasetError
from data_modules.io import atomic_write
from tivne.field.networks import TimeVaryingField


def save_checkpoint(
    path: str | Path,
    field: TimeVaryingField,
    field_kwargs: dict[str, Any],
    timestamps: list[float],
    poses: torch.Tensor,
    t0: float,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write the field and trajectory atomically (tmp file + rename).

    Args:
        field_kwargs: the keyword arguments the field was built with (rebuilds it on load).
        timestamps: (N,) seconds of the processed frames; poses: (N, 4, 4) c2w; t0: the time of τ = 0.
    """
    payload = {
        "format": 1,
        "field_kwargs": dict(field_kwargs),
        "field_state": {k: v.detach().cpu() for k, v in field.state_dict().items()},
        "timestamps": [float(t) for t in timestamps],
        "poses": poses.detach().cpu().double(),
        "t0": float(t0),
        "extra": extra or {},
    }
    return atomic_write(path, lambda tmp: torch.save(payload, tmp))


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[TimeVaryingField, dict[str, Any]]:
    """Rebuild the field from a checkpoint; returns (field in eval mode, payload without the state)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a truncated or foreign file
        raise DatasetError(path, f"not a readable TivNe checkpoint ({type(exc).__name__})") from None
    try:
        field = TimeVaryingField(**payload["field_kwargs"])
        state = dict(payload["field_state"])
        field.grid.load_sparse_state({k[len("grid."):]: v for k, v in state.items() if k.startswith("grid.")})
        for name in ("voxel_hits", "dynamic_keys", "dynamic_tau"):  # format-1 files from before hit counts
            state.setdefault(f"grid.{name}", getattr(field.grid, name))
        field.load_state_dict(state)
    except (KeyError, TypeError, RuntimeError) as exc:  # written by an incompatible version
        first_line = str(exc).strip().splitlines()[-1].strip()
        raise DatasetError(path, f"checkpoint does not match this version of the field ({first_line})") from None
    field.to(device).eval()
    meta = {k: v for k, v in payload.items() if k != "field_state"}
    return field, meta


def camera_centres(meta: dict[str, Any]) -> np.ndarray:
    """(N, 3) camera positions of a checkpoint's trajectory (SLAM frame), from ``meta["poses"]``."""
    poses = meta.get("poses")
    if poses is None:
        return np.zeros((0, 3))
    return np.asarray(torch.as_tensor(poses, dtype=torch.float64)[:, :3, 3])
