"""A run's checkpoint, ``checkpoints/slam.pt``: the field, its config section, the clock and the
trajectory (what ``tivne.mesh`` and ``tivne.evaluate`` read), plus the whole state of the run
(``resume``) so that ``tivne.train ... resume=true`` continues an interrupted run where it stood.

The resume state is taken between two frames (every ``output.checkpoint_every`` frames, before the
final pass, on SIGINT / SIGTERM): :meth:`tivne.slam.loop.SlamLoop.state_dict` (the map optimiser,
the keyframe store with its poses, the per-frame pose records, the tracker's reference and counters,
the mask provider's state, the clock, timers, the loop's generator and the position in the stream)
plus the global RNGs. Restored, a run continues as the uninterrupted one would have.

Every file is written atomically; a missing, truncated or foreign file is one :class:`DatasetError`
line, never a deserialiser's traceback.
"""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from data_modules.frame import DatasetError
from data_modules.io import atomic_write
from tivne.config import ConfigError, FieldConfig
from tivne.field.clock import Clock
from tivne.field.networks import TimeVaryingField
from tivne.field.object_state import restore_objects
from tivne.meshing import DepthViews
from tivne.slam.keyframes import view_from_state
from tivne.slam.outputs import RunDirError, config_differences, describe_differences

# 1: field + trajectory; 2: + the resume state and the run's config; 3: the field's config section
# and the clock (was: constructor arguments and t0), the loop's state (no copy of the motion poses);
# 4: the tracker's stored references (each frame's pyramid source) instead of one reference pyramid
FORMAT = 4


def save_checkpoint(
    path: str | Path,
    field: TimeVaryingField,
    timestamps: list[float],
    poses: torch.Tensor,
    clock: Clock,
    extra: dict[str, Any] | None = None,
    resume: dict[str, Any] | None = None,
    config: dict[str, Any] | None = None,
) -> Path:
    """Write the field and trajectory atomically (tmp file + rename).

    Args:
        field: saved with its config section (``field.cfg``, which rebuilds it on load).
        timestamps: (N,) seconds of the processed frames; poses: (N, 4, 4) c2w; clock: τ of a timestamp.
        resume: the loop's state and the global RNGs (None: a checkpoint that cannot be resumed).
        config: the run's composed config (plain values), which a resumed run must repeat.
    Raises:
        OSError: naming ``path`` (full disk, read-only folder); the old file stays as it was.
    """
    payload = {
        "format": FORMAT,
        "field_config": dataclasses.asdict(field.cfg),
        "field_state": {k: v.detach().cpu() for k, v in field.state_dict().items()},
        "timestamps": [float(t) for t in timestamps],
        "poses": poses.detach().cpu().double(),
        "clock": clock.state_dict(),
        "extra": extra or {},
        "config": config,
        "resume": None if resume is None else to_device(resume, "cpu"),
    }
    return atomic_write(path, lambda tmp: torch_save(payload, tmp))


def torch_save(payload: Any, path: Path) -> None:
    """torch.save through a Python file: a full disk is then an OSError (ENOSPC), not a RuntimeError."""
    with open(path, "wb") as fh:
        torch.save(payload, fh)


def read_checkpoint(path: str | Path, mmap: bool = False) -> dict[str, Any]:
    """The payload of a checkpoint file, or a one-line DatasetError naming it (missing, truncated,
    not a TivNe checkpoint). ``mmap``: map the tensors instead of reading them (the field alone of
    a file that also holds the keyframes)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "checkpoint not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as exc:  # noqa: BLE001 -- a truncated or foreign file, whatever the reader says
        raise DatasetError(path, f"not a readable TivNe checkpoint (truncated or another kind of file: {type(exc).__name__})") from None
    if not isinstance(payload, dict) or "field_state" not in payload or "timestamps" not in payload:
        raise DatasetError(path, "not a TivNe checkpoint (no field state)")
    if payload.get("format") != FORMAT:
        raise DatasetError(path, f"written by another version of TivNe (checkpoint format {payload.get('format')}, this version reads {FORMAT}); re-run it")
    return payload


def load_field_state(field: TimeVaryingField, state: dict[str, torch.Tensor]) -> None:
    """Load a field state dict into ``field`` (its grid grows to the saved size first)."""
    state = dict(state)
    field.grid.load_sparse_state({k[len("grid."):]: v for k, v in state.items() if k.startswith("grid.")})
    for name in ("voxel_hits", "dynamic_keys", "dynamic_tau", "surface_keys"):  # files from before these records
        state.setdefault(f"grid.{name}", getattr(field.grid, name))
    field.load_state_dict(state)


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[TimeVaryingField, dict[str, Any]]:
    """Rebuild the field from a checkpoint; returns (field in eval mode, payload without the field
    and resume state)."""
    path = Path(path)
    payload = read_checkpoint(path, mmap=True)
    try:
        field = TimeVaryingField(FieldConfig.from_mapping(payload["field_config"]))
        load_field_state(field, payload["field_state"])
        field = restore_objects(field, payload.get("extra"))  # field=objects: its object fields
    except (KeyError, TypeError, RuntimeError, ConfigError) as exc:  # written by an incompatible version
        first_line = str(exc).strip().splitlines()[-1].strip()
        raise DatasetError(path, f"checkpoint does not match this version of the field ({first_line})") from None
    field.to(device).eval()
    meta = {k: v for k, v in payload.items() if k not in ("field_state", "resume")}
    meta["clock"] = Clock.from_state(payload["clock"])
    meta["depth_views"] = stored_depth_views(payload)
    return field, meta


def stored_depth_views(payload: dict[str, Any]) -> DepthViews | None:
    """The keyframes a resumable checkpoint holds, with their depth intrinsics, for carving meshes
    (:func:`tivne.meshing.carve_free_space`); None for a checkpoint without them (not resumable, or
    written before the intrinsics were saved)."""
    resume, K = payload.get("resume"), (payload.get("extra") or {}).get("K")
    views = ((resume or {}).get("keyframes") or {}).get("views")
    if K is None or not views:
        return None
    return DepthViews([view_from_state(v) for v in views], torch.as_tensor(K))


def camera_centres(meta: dict[str, Any]) -> np.ndarray:
    """(N, 3) camera positions of a checkpoint's trajectory (SLAM frame), from ``meta["poses"]``."""
    poses = meta.get("poses")
    if poses is None:
        return np.zeros((0, 3))
    return np.asarray(torch.as_tensor(poses, dtype=torch.float64)[:, :3, 3])


# ------------------------------------------------------------------------------------ resume


def global_rng_state() -> dict[str, Any]:
    """torch (CPU and CUDA), numpy and Python RNG states, in types a weights-only load accepts."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() and torch.cuda.is_initialized() else None,
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos), "has_gauss": int(has_gauss), "gauss": float(gauss)},
        "python": random.getstate(),
    }


def set_global_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"].cpu())
    if state.get("cuda") is not None and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["gauss"]))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))


def to_device(tree: Any, device: torch.device | str) -> Any:
    """Every tensor of a nested dict / list / tuple moved to ``device`` (other values as they are)."""
    if isinstance(tree, torch.Tensor):
        return tree.to(device)
    if isinstance(tree, dict):
        return {k: to_device(v, device) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(to_device(v, device) for v in tree)
    return tree


def resume_state_of(path: str | Path, payload: dict[str, Any]) -> dict[str, Any]:
    """The resume state of a checkpoint payload, or a one-line RunDirError when it has none."""
    state = payload.get("resume")
    if not isinstance(state, dict) or "position" not in state:
        raise RunDirError(path, "holds no resume state (written by an older version or during the final pass); run without resume=true")
    return state


def check_resumable(path: str | Path) -> None:
    """Refuse (one line) a checkpoint that cannot be resumed: missing, unreadable or without a
    resume state. Cheap (the tensors are mapped, not read): for a check before anything is written."""
    resume_state_of(path, read_checkpoint(path, mmap=True))


def load_resume_state(path: str | Path, config: dict[str, Any], timestamps: np.ndarray) -> dict[str, Any]:
    """The checkpoint payload to resume a run from, checked against this run: the same ``config``
    (but for where it runs) and a sequence whose first frames are the ones already processed
    (``timestamps``: the whole stream's, seconds). Raises one-line DatasetError / RunDirError."""
    path = Path(path)
    payload = read_checkpoint(path)
    state = resume_state_of(path, payload)
    if payload.get("config") is not None:
        differ = config_differences(payload["config"], config)
        if differ:
            raise RunDirError(path, "resume=true with a different config: " + describe_differences(differ))
    done = [float(t) for t in payload["timestamps"]]
    position = int(state["position"])
    stream = [float(t) for t in timestamps[:position]]
    if position != len(done) or position > len(timestamps) or not np.allclose(done, stream, rtol=0, atol=1e-6):
        raise RunDirError(path, f"its {len(done)} processed frames are not the first frames of this sequence ({len(timestamps)} frames)")
    return payload
