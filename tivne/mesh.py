"""Export meshes of a finished run at chosen times: a 4D mesh sequence.

    python -m tivne.mesh run_dir=PATH [mesh.times=[t1,t2,...] | every=k] [mesh.resolution=0.02] [device=cpu]

``mesh.times`` are seconds on the sequence clock (as written in run_dir/trajectory.txt); ``every=k`` meshes
every k-th processed frame; by default the first and last processed frame. Times outside the
recorded range [first, last] by more than 1 ms are refused (the field was never trained there); times
within 1 ms outside are clamped to the range. Meshes go to run_dir/meshes/mesh_t{t:.3f}.ply, one line
per mesh on stdout. Errors are one ``error: ...`` line on stderr and exit status 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from data_modules.errors import overrides_checked
from tivne.cli import check_known_keys, mesh_settings, one_line_errors, quote_run_dir, register_defaults
from tivne.config import MeshConfig
from tivne.meshing import mesh_at, save_mesh, select_mesh_times
from tivne.slam.checkpoint import camera_centres, load_checkpoint
from tivne.slam.outputs import RunDir
from tivne.utils import require_device

register_defaults()

def mesh_run(
    run_dir: str | Path, cfg: MeshConfig = MeshConfig(), every: int | None = None, device: str | None = None
) -> list[tuple[float, int, int, Path]]:
    """Mesh a run's checkpoint at ``cfg.times`` (empty: first and last frame) or every ``every``-th
    processed frame, with ``cfg``'s resolution and culling, and write the PLYs.

    Returns:
        (time s, vertices, faces, path) per mesh.
    Raises:
        FileNotFoundError: no run dir; DatasetError: no or a bad checkpoint; ConfigError: bad times
        or a device this torch does not have; OSError: a mesh cannot be written (naming it).
    """
    device = require_device(device) if device else ("cuda" if torch.cuda.is_available() else "cpu")
    run = RunDir(run_dir)
    if not run.root.is_dir():
        raise FileNotFoundError(f"{run.root}: run directory not found")
    field, meta = load_checkpoint(run.checkpoint, device=device)
    run.check_writable()  # before marching cubes, not after
    written = []
    cache: dict = {}  # field=objects: the static field and rigid objects are meshed once
    for ts in select_mesh_times(meta["timestamps"], list(cfg.times) or None, every):
        tau = meta["clock"].tau(ts)
        mesh = mesh_at(field, tau, cfg, camera_centres(meta), cache, meta["depth_views"])
        path = save_mesh(mesh, run.mesh_path(ts))
        written.append((ts, len(mesh.vertices), len(mesh.faces), path))
    return written


@overrides_checked
@hydra.main(config_path="../conf", config_name="mesh", version_base="1.3")
@one_line_errors
def main(cfg: DictConfig) -> None:
    check_known_keys(cfg, ("run_dir", "every", "device", "mesh"))
    written = mesh_run(cfg.run_dir, mesh_settings(cfg.mesh), cfg.every, cfg.device)
    for ts, n_verts, n_faces, path in written:
        if n_faces == 0:
            print(f"warning: empty mesh at t={ts:.3f}s (no surface inside the allocated voxels)", file=sys.stderr)
        print(f"t={ts:.3f}s vertices={n_verts} faces={n_faces} path={path}")


if __name__ == "__main__":
    sys.argv = quote_run_dir(sys.argv)  # a sweep job dir as printed (tivne.cli.quote_run_dir)
    main()
