"""Export meshes of a finished run at chosen times: a 4D mesh sequence.

    python -m tivne.mesh run_dir=PATH [times=[t1,t2,...]] [every=k] [resolution=0.02]

times are seconds on the sequence clock (as in trajectory.txt); every=k meshes every k-th processed
frame; by default the first and last frame. Times outside the recorded range are refused.
"""

from __future__ import annotations

import sys
from pathlib import Path

from tivne.checkpoint import CHECKPOINT_NAME, load_checkpoint, time_to_tau
from tivne.meshing import extract_mesh, save_mesh


def parse_args(argv: list[str]) -> dict[str, str]:
    args = {}
    for item in argv:
        if "=" not in item:
            raise ValueError(f"expected key=value, got {item!r}")
        key, value = item.split("=", 1)
        args[key] = value
    return args


def mesh_times(timestamps: list[float], times: str | None, every: str | None) -> list[float]:
    if times:
        values = [float(v) for v in times.strip("[]").split(",") if v.strip()]
        lo, hi = timestamps[0], timestamps[-1]
        bad = [t for t in values if not lo - 1e-6 <= t <= hi + 1e-6]
        if bad:
            raise ValueError(f"times {bad} are outside the recorded range [{lo:.3f}, {hi:.3f}] s")
        return values
    if every:
        return timestamps[:: max(int(every), 1)]
    return [timestamps[0], timestamps[-1]]


def main(argv: list[str]) -> int:
    try:
        args = parse_args(argv)
        run_dir = Path(args["run_dir"]) if "run_dir" in args else None
        if run_dir is None:
            raise ValueError("run_dir=PATH is required")
        field, meta = load_checkpoint(run_dir / "checkpoints" / CHECKPOINT_NAME)
        times = mesh_times(meta["timestamps"], args.get("times"), args.get("every"))
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    resolution = float(args.get("resolution", 0.02))
    for ts in times:
        mesh = extract_mesh(field, time_to_tau(ts, meta["t0"], field.time_scale), resolution)
        path = save_mesh(mesh, run_dir / "meshes" / f"mesh_t{ts:.3f}.ply")
        print(f"t={ts:.3f}s vertices={len(mesh.vertices)} faces={len(mesh.faces)} -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
