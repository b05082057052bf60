"""Time of a 4D mesh sequence: a run's checkpoint meshed at N evenly spaced processed times.

    python bench/mesh4d.py RUN_DIR [--count 30] [--threads 2] [--resolution 0.02]

One :func:`tivne.meshing.mesh_at` cache for the whole sequence, as ``tivne.mesh`` uses it: with
``field=objects`` the static field (no time) and each rigid object are meshed once and the objects
placed per time; with ``field=tivne`` every time is a full marching-cubes pass. Prints the total,
the first mesh (which pays for the cached parts) and the mean of the others. Figures only.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tivne.config import MeshConfig  # noqa: E402
from tivne.meshing import mesh_at  # noqa: E402
from tivne.slam.checkpoint import camera_centres, load_checkpoint  # noqa: E402
from tivne.slam.outputs import RunDir  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir")
    parser.add_argument("--count", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--resolution", type=float, default=MeshConfig().resolution)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cfg = MeshConfig(resolution=args.resolution)
    field, meta = load_checkpoint(RunDir(args.run_dir).checkpoint)
    stamps = np.asarray(meta["timestamps"])
    times = stamps[np.linspace(0, len(stamps) - 1, args.count).round().astype(int)]
    cache: dict = {}
    seconds, faces = [], []
    for t in times:
        start = time.perf_counter()
        mesh = mesh_at(field, meta["clock"].tau(float(t)), cfg, camera_centres(meta), cache, meta["depth_views"])
        seconds.append(time.perf_counter() - start)
        faces.append(len(mesh.faces))
    kind = type(field).__name__
    print(f"bench/mesh4d.py {args.run_dir}: {kind}, {args.count} meshes at resolution {cfg.resolution} m, {args.threads} threads")
    print(f"total {sum(seconds):.1f} s; first {seconds[0]:.1f} s; others mean {np.mean(seconds[1:]) if len(seconds) > 1 else 0:.2f} s; "
          f"faces {min(faces)}-{max(faces)}")


if __name__ == "__main__":
    main()
