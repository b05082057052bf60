"""Evaluate a finished run: trajectory against GT, and meshes against GT geometry where the dataset has it.

    python -m tivne.evaluate run_dir=path/to/run [mesh_resolution=0.02]

Results are merged into run_dir/metrics.json (flat keys with units; null plus a ``*_reason`` key
where not computable).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tivne.checkpoint import CHECKPOINT_NAME, load_checkpoint, time_to_tau
from tivne.geometry import backproject, invert_pose, pixel_grid, read_tum_trajectory, transform_points
from tivne.meshing import extract_mesh
from tivne.metrics import ate_from_trajectories, ghost_fraction, mesh_metrics, sample_mesh_surface, nearest_distances

THRESHOLD_M = 0.05
CUBE_MARGIN_M = 0.05


def observed_static_surface(view, first_pose: torch.Tensor, every: int = 10, per_frame: int = 4000, seed: int = 0) -> np.ndarray:
    """GT surface the camera saw: static, valid depth of every ``every``-th frame back-projected with GT
    poses into the SLAM frame (the first camera's). Returns (M, 3) float64."""
    rng = np.random.default_rng(seed)
    K = view.intrinsics.K(dtype=torch.float64)
    to_slam = invert_pose(first_pose.double())
    points = []
    for i in range(0, len(view), every):
        f = view[i]
        if f.gt_pose is None:
            continue
        keep = f.depth > 0
        if f.mask is not None:
            keep &= ~f.mask
        uv = pixel_grid(f.height, f.width, dtype=torch.float64)[keep]
        idx = rng.choice(len(uv), size=min(per_frame, len(uv)), replace=False)
        cam = backproject(uv[idx], f.depth.double()[keep][idx], K)
        points.append(transform_points(to_slam @ f.gt_pose.double(), cam).numpy())
    return np.concatenate(points) if points else np.zeros((0, 3))


def cube_mesh_metrics(field, meta: dict[str, Any], dataset, view, times: list[float], resolution: float) -> dict[str, Any]:
    """Mesh metrics at each time: cube-region accuracy/completion, ghost fraction, static completion."""
    first_pose = torch.as_tensor(dataset.camera_pose(int(view.source_indices[0])), dtype=torch.float64)
    to_slam = invert_pose(first_pose).numpy()

    def slam(points: np.ndarray) -> np.ndarray:
        return points @ to_slam[:3, :3].T + to_slam[:3, 3]

    observed = observed_static_surface(view, first_pose)
    out: dict[str, Any] = {}
    for label, ts in zip(("first", "last"), times):
        mesh = extract_mesh(field, time_to_tau(ts, meta["t0"], field.time_scale), resolution)
        key = f"mesh_t{ts:.2f}"
        if len(mesh.faces) == 0:
            out[f"{key}_reason"] = "empty mesh"
            continue
        pred = sample_mesh_surface(mesh, 200_000, seed=0)
        gt_dyn = slam(dataset.sample_surface(ts, 50_000, part="dynamic", seed=1))
        gt_all = slam(dataset.sample_surface(ts, 200_000, part="all", seed=2))
        center, half, R = dataset.dynamic_box(ts)
        box_local = (pred - slam(np.asarray(center)[None])) @ (to_slam[:3, :3] @ np.asarray(R))
        in_box = (np.abs(box_local) <= np.asarray(half) + CUBE_MARGIN_M).all(1)
        cube = mesh_metrics(pred[in_box], gt_dyn, THRESHOLD_M) if in_box.any() else {}
        values = {
            "cube_accuracy_m": cube.get("accuracy_m"),
            "cube_completion_ratio": cube.get("completion_ratio"),
            "ghost_fraction": float(ghost_fraction(pred, gt_all, THRESHOLD_M)),
            "static_completion_ratio": float((nearest_distances(observed, pred) <= THRESHOLD_M).mean()) if len(observed) else None,
            "static_accuracy_m": float(nearest_distances(pred[~in_box], gt_all).mean()),
        }
        for name, value in values.items():
            out[f"{key}_{name}"] = value
            stem, unit = (name[:-2], "_m") if name.endswith("_m") else (name, "")
            out[f"{stem}_{label}{unit}"] = value  # e.g. cube_accuracy_first_m
    return out


def evaluate_run(run_dir: str | Path, dataset_view=None, mesh_resolution: float = 0.02) -> dict[str, Any]:
    """Flat, JSON-serialisable metrics of a run directory."""
    run_dir = Path(run_dir)
    result: dict[str, Any] = {}
    if dataset_view is None:
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        from data_modules.sequence import SequenceView

        cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
        dataset_view = SequenceView(instantiate(cfg.dataset), **OmegaConf.to_container(cfg.data, resolve=True))
    dataset = dataset_view.base
    if getattr(dataset, "has_gt_poses", False) and hasattr(dataset, "camera_pose"):
        ts_est, est = read_tum_trajectory(run_dir / "trajectory.txt")
        gt = np.stack([dataset.camera_pose(int(i)) for i in dataset_view.source_indices])
        result.update(ate_from_trajectories(ts_est, est.numpy(), dataset_view.timestamps, gt).as_metrics())
    field, meta = load_checkpoint(run_dir / "checkpoints" / CHECKPOINT_NAME)
    times = [meta["timestamps"][0], meta["timestamps"][-1]]
    if hasattr(dataset, "sample_surface") and hasattr(dataset, "dynamic_box"):
        result.update(cube_mesh_metrics(field, meta, dataset, dataset_view, times, mesh_resolution))
    else:
        result["mesh_metrics_reason"] = "the dataset has no ground-truth geometry"
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in result.items()}


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv if "=" in a)
    if "run_dir" not in args:
        print("error: usage: python -m tivne.evaluate run_dir=PATH [mesh_resolution=0.02]", file=sys.stderr)
        return 2
    run_dir = Path(args["run_dir"])
    try:
        metrics = evaluate_run(run_dir, mesh_resolution=float(args.get("mesh_resolution", 0.02)))
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from tivne.system import write_metrics

    write_metrics(run_dir / "metrics.json", metrics)
    print(json.dumps(metrics, indent=2, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
