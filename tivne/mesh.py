"""Export meshes of a finished run at chosen times: a 4D mesh sequence.

    python -m tivne.mesh run_dir=PATH [times=[t1,t2,...] | every=k] [resolution=0.02] [device=cpu]

``times`` are seconds on the sequence clock (as written in run_dir/trajectory.txt); ``every=k`` meshes
every k-th processed frame; by default the first and last processed frame. Times outside the
recorded range [first, last] by more than 1 ms are refused (the field was never trained there); times
within 1 ms outside are clamped to the range. Meshes go to run_dir/meshes/mesh_t{t:.3f}.ply, one line
per mesh on stdout. Errors are one ``error: ...`` line on stderr and exit status 2.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from tivne.checkpoint import CHECKPOINT_NAME, camera_centres, load_checkpoint, time_to_tau
from tivne.meshing import MeshCulling, extract_mesh, save_mesh

TIME_TOLERANCE_S = 1e-3


def select_mesh_times(
    timestamps: Sequence[float], times: Sequence[float] | None = None, every: int | None = None
) -> list[float]:
    """Times to mesh, in seconds on the sequence clock.

    Args:
        timestamps: (N,) processed frames' timestamps, increasing, N >= 1.
        times: explicit times; each must lie in [first, last] (within ``TIME_TOLERANCE_S``, clamped).
        every: every k-th processed frame (k >= 1) instead.
    Returns:
        the times; by default the first and last timestamp (one when they coincide).
    Raises:
        ValueError: both ``times`` and ``every``, a bad ``every``, or a time outside the range.
    """
    if not len(timestamps):
        raise ValueError("the checkpoint records no processed frames")
    lo, hi = float(timestamps[0]), float(timestamps[-1])
    if times is not None and every is not None:
        raise ValueError("give either times=[...] or every=k, not both")
    if every is not None:
        if int(every) != every or every < 1:
            raise ValueError(f"every must be an integer >= 1, got {every}")
        return [float(t) for t in timestamps[:: int(every)]]
    if times is None:
        return [lo] if hi == lo else [lo, hi]
    values = [float(t) for t in times]
    bad = [t for t in values if not lo - TIME_TOLERANCE_S <= t <= hi + TIME_TOLERANCE_S]
    if bad:
        raise ValueError(f"times {bad} lie outside the recorded range [{lo:.3f}, {hi:.3f}] s")
    return [min(max(t, lo), hi) for t in values]


def mesh_path(run_dir: str | Path, timestamp: float) -> Path:
    """run_dir/meshes/mesh_t{t:.3f}.ply."""
    return Path(run_dir) / "meshes" / f"mesh_t{timestamp:.3f}.ply"


def mesh_run(
    run_dir: str | Path,
    times: Sequence[float] | None = None,
    every: int | None = None,
    resolution: float = 0.02,
    device: str | None = None,
    culling: MeshCulling | None = MeshCulling(),
) -> list[tuple[float, int, int, Path]]:
    """Mesh a run's checkpoint at the selected times and write the PLYs.

    ``culling``: see :class:`tivne.meshing.MeshCulling` (default: observed space only).

    Returns:
        (time s, vertices, faces, path) per mesh.
    Raises:
        FileNotFoundError: no run dir / checkpoint; ValueError: bad times or checkpoint.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: run directory not found")
    if resolution <= 0:
        raise ValueError(f"resolution must be positive, got {resolution}")
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    field, meta = load_checkpoint(run_dir / "checkpoints" / CHECKPOINT_NAME, device=device)
    written = []
    for ts in select_mesh_times(meta["timestamps"], times, every):
        tau = time_to_tau(ts, meta["t0"], field.time_scale)
        mesh = extract_mesh(field, tau, resolution, culling=culling, camera_centres=camera_centres(meta))
        path = save_mesh(mesh, mesh_path(run_dir, ts))
        written.append((ts, len(mesh.vertices), len(mesh.faces), path))
    return written


@hydra.main(config_path="../conf", config_name="mesh", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        times = cfg.times
        if times is not None and not OmegaConf.is_list(times):
            times = [times]  # times=1.5
        culling = MeshCulling(int(cfg.min_hits), cfg.dynamic_window, bool(cfg.backfaces))
        written = mesh_run(cfg.run_dir, times, cfg.every, float(cfg.resolution), cfg.device, culling)
    except (FileNotFoundError, ValueError, MissingMandatoryValue) as exc:
        print(f"error: {exc}".splitlines()[0], file=sys.stderr)
        sys.exit(2)
    for ts, n_verts, n_faces, path in written:
        if n_faces == 0:
            print(f"warning: empty mesh at t={ts:.3f}s (no surface inside the allocated voxels)", file=sys.stderr)
        print(f"t={ts:.3f}s vertices={n_verts} faces={n_faces} path={path}")


if __name__ == "__main__":
    main()
