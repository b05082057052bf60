"""Evaluate a finished run: trajectory against GT, and meshes against GT geometry where the dataset has it.

The command line is :mod:`tivne.evaluate`. The dataset is rebuilt from the run's own config
(run_dir/.hydra/config.yaml); results are flat keys with units (null plus a ``*_reason`` key where
not computable).

Mesh metrics (datasets with GT geometry: ``sample_surface`` and ``dynamic_box``, i.e. the moving cube)
at each mesh time t, computed in the dataset's world frame (distances do not change under the rigid map
between the frames, so this equals comparing in the SLAM frame):
    * SLAM -> world: ``frame="first_camera"`` (default): the SLAM world frame is the first camera's,
      so p_world = G0 p_slam with G0 the GT pose of the first processed frame; the mesh error then
      includes the drift of the frames that built it. ``frame="ate"``: the SE(3) alignment of the ATE
      (spreads the trajectory error, more robust to a bad first pose).
    * ``cube_accuracy_m``: mean distance from reconstructed surface samples inside the moving object's
      GT box at t (dilated by ``cube_margin_m``) to the GT dynamic surface at t;
      ``cube_completion_ratio``: share of GT dynamic surface samples at t within ``threshold_m`` of the
      mesh (the whole GT cube surface, also faces the camera never saw).
    * ``ghost_fraction``: share of reconstructed samples farther than ``threshold_m`` from the whole GT
      surface (static + dynamic) at t.
    * ``static_completion_ratio``: share of the OBSERVED static surface within ``threshold_m`` of the
      mesh; the observed surface is the back-projected static (mask False), valid depth of every
      ``static_every``-th processed frame with GT poses (noise-free depth where the dataset can render
      it); ``static_accuracy_m``: mean distance from reconstructed samples outside the dilated object
      boxes to the GT static surface.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import trimesh
from omegaconf import OmegaConf

from data_modules.frame import DatasetError
from data_modules.tables import read_tum_trajectory
from tivne.config import MeshConfig, MeshEvalSettings
from tivne.field.networks import time_to_tau
from tivne.geometry import backproject, pixel_grid
from tivne.meshing import extract_mesh
from tivne.metrics.surface import nearest_distances, sample_mesh_surface
from tivne.metrics.trajectory import ate_from_trajectories
from tivne.slam.checkpoint import camera_centres, load_checkpoint
from tivne.slam.outputs import RunDir, jsonable

ATE_KEYS = ("ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_std_m", "ate_max_m")
MESH_VALUE_KEYS = (
    "cube_accuracy_m",
    "cube_completion_ratio",
    "ghost_fraction",
    "static_completion_ratio",
    "static_accuracy_m",
)
SlamFrame = Literal["first_camera", "ate"]


# --------------------------------------------------------------------------------------------------
# Trajectory
# --------------------------------------------------------------------------------------------------


def gt_trajectory(view) -> tuple[np.ndarray, np.ndarray]:
    """GT camera poses of the view's frames that have one.

    Args:
        view: a SequenceView (or any SequenceDataset with ``camera_pose``).
    Returns:
        timestamps (K,) seconds and poses (K, 4, 4) float64 c2w; K = 0 without GT.
    """
    if not getattr(view, "has_gt_poses", False):
        return np.zeros(0), np.zeros((0, 4, 4))
    base = getattr(view, "base", view)
    indices = getattr(view, "source_indices", np.arange(len(view)))
    ts, poses = [], []
    for i, src in enumerate(indices):
        try:
            pose = base.camera_pose(int(src))
        except DatasetError:  # outside the GT coverage
            continue
        ts.append(float(view.timestamps[i]))
        poses.append(np.asarray(torch.as_tensor(pose, dtype=torch.float64)))
    if not ts:
        return np.zeros(0), np.zeros((0, 4, 4))
    return np.asarray(ts), np.stack(poses)


def null_ate(reason: str) -> dict[str, Any]:
    return {**{k: None for k in ATE_KEYS}, "ate_frames": None, "ate_reason": reason}


def trajectory_metrics(
    ts_est: np.ndarray, est_poses: np.ndarray, ts_gt: np.ndarray, gt_poses: np.ndarray, max_diff: float = 0.02
) -> tuple[dict[str, Any], Any]:
    """ATE (SE(3)-aligned, associated by timestamp) as metrics.json keys.

    Args:
        ts_est: (N,), est_poses: (N, 4, 4); ts_gt: (M,), gt_poses: (M, 4, 4).
    Returns:
        ({ate_rmse_m, ate_mean_m, ate_median_m, ate_std_m, ate_max_m, ate_frames} or nulls with
        ``ate_reason``) and the ATEResult (None when not computable).
    """
    if len(ts_gt) == 0:
        return null_ate("the dataset has no ground-truth poses for these frames"), None
    try:
        result = ate_from_trajectories(ts_est, est_poses, ts_gt, gt_poses, max_diff=max_diff, align="se3")
    except ValueError as exc:
        return null_ate(str(exc)), None
    if result.num_poses < 3:
        return null_ate(f"only {result.num_poses} estimated poses match a ground-truth pose (need 3)"), None
    return {**result.as_metrics(), "ate_frames": int(result.num_poses)}, result


# --------------------------------------------------------------------------------------------------
# Ground-truth geometry
# --------------------------------------------------------------------------------------------------


def has_gt_geometry(dataset) -> bool:
    """True for datasets exposing exact geometry (``sample_surface`` and ``dynamic_box``)."""
    return hasattr(dataset, "sample_surface") and hasattr(dataset, "dynamic_box")


def object_boxes(dataset, t: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(center (3,), half extents (3,), R (3, 3)) of every moving object at time t, world frame."""
    boxes = []
    for name in getattr(dataset, "object_names", ["cube"]):
        c, h, R = dataset.dynamic_box(t, name)
        boxes.append(tuple(np.asarray(torch.as_tensor(x, dtype=torch.float64)) for x in (c, h, R)))
    return boxes


def in_boxes(points: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], margin: float) -> np.ndarray:
    """(N, 3) world points -> (N,) bool, inside any oriented box dilated by ``margin`` metres."""
    inside = np.zeros(len(points), dtype=bool)
    for c, h, R in boxes:
        local = (points - c) @ R  # R^T (p - c) for each row
        inside |= (np.abs(local) <= h + margin).all(1)
    return inside


def observed_static_surface(view, every: int = 10, per_frame: int = 5_000, seed: int = 0) -> np.ndarray:
    """The static surface the camera saw, in the world frame.

    Back-projects the valid, static (mask False or no mask) depth pixels of every ``every``-th frame of
    the view with the GT pose, ``per_frame`` random pixels per frame. Where the base dataset can render
    noise-free frames (``render(i, noise=False)``) and the view does not resize, the exact depth is
    used (the view's depth range still applies), so sensor noise does not enter the GT.

    Returns:
        (M, 3) float64 world points; (0, 3) without GT poses.
    """
    rng = np.random.default_rng(seed)
    base = getattr(view, "base", view)
    indices = getattr(view, "source_indices", np.arange(len(view)))
    exact = hasattr(base, "render") and getattr(view, "size", None) is None
    K = view.intrinsics.K(dtype=torch.float64)
    points = []
    for i in range(0, len(view), max(1, int(every))):
        if exact:
            frame = base.render(int(indices[i]), noise=False)
            depth = frame.depth.double()
            invalid = depth < getattr(view, "depth_min", 0.0)
            if getattr(view, "depth_max", None) is not None:
                invalid |= depth > view.depth_max
            depth = torch.where(invalid, torch.zeros_like(depth), depth)
        else:
            frame = view[i]
            depth = frame.depth.double()
        if frame.gt_pose is None:
            continue
        keep = depth > 0
        if frame.mask is not None:
            keep &= ~frame.mask
        uv = pixel_grid(frame.height, frame.width, dtype=torch.float64)[keep]
        if len(uv) == 0:
            continue
        pick = torch.from_numpy(rng.choice(len(uv), size=min(per_frame, len(uv)), replace=False))
        cam = backproject(uv[pick], depth[keep][pick], K)
        pose = frame.gt_pose.double()
        points.append((cam @ pose[:3, :3].T + pose[:3, 3]).numpy())
    return np.concatenate(points) if points else np.zeros((0, 3))


def transform(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(N, 3) points through a (4, 4) transform."""
    return points @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------------------------------
# Mesh metrics
# --------------------------------------------------------------------------------------------------


DistanceFn = Callable[[np.ndarray, str], np.ndarray]


def gt_distance_fn(dataset, t: float, settings: MeshEvalSettings = MeshEvalSettings()) -> DistanceFn:
    """Distance (N,) from (N, 3) world points to the GT surface at t: ``fn(points, part)``.

    Exact ``|sdf(points, t, part)|`` where the dataset has an exact SDF (no bias from the GT samples'
    density; the room interior and the objects' outsides are exact distances), else the distance to
    ``settings.gt_samples`` surface samples. ``part``: "all", "static" or "dynamic".
    """
    if hasattr(dataset, "sdf"):

        def exact(points: np.ndarray, part: str) -> np.ndarray:
            if len(points) == 0:
                return np.zeros(0)
            return np.abs(np.asarray(dataset.sdf(torch.from_numpy(np.asarray(points, dtype=np.float64)), t, part=part)))

        return exact
    samples: dict[str, np.ndarray] = {}

    def sampled(points: np.ndarray, part: str) -> np.ndarray:
        if part not in samples:
            salt = {"all": 1, "static": 3, "dynamic": 2}[part]
            samples[part] = np.asarray(dataset.sample_surface(t, settings.gt_samples, part=part, seed=settings.seed + salt))
        return nearest_distances(points, samples[part])

    return sampled


def mesh_time_metrics(
    pred: np.ndarray,
    pred_cube: np.ndarray,
    gt_dynamic: np.ndarray,
    observed_static: np.ndarray,
    boxes: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    distance: DistanceFn,
    settings: MeshEvalSettings = MeshEvalSettings(),
) -> dict[str, Any]:
    """Mesh metrics at one time t, all points in the same (world) frame.

    Args:
        pred: (N, 3) samples of the reconstructed surface at t.
        pred_cube: (C, 3) samples of the part of that surface near the moving objects (sampled on its
            own, so its density does not depend on the size of the scene); points outside the dilated
            boxes are dropped here.
        gt_dynamic: (M, 3) GT samples of the moving objects' surface at t (for completion).
        observed_static: (S, 3) GT static surface the camera observed (for completion).
        boxes: moving objects' oriented boxes at t (see :func:`object_boxes`).
        distance: distance to the GT surface at t (see :func:`gt_distance_fn`), for accuracy / ghosts.
    Returns:
        the :data:`MESH_VALUE_KEYS` values (None where not computable) plus ``reason`` /
        ``cube_reason`` / ``static_reason`` when something is missing.
    """
    thr = settings.threshold_m
    out: dict[str, Any] = {k: None for k in MESH_VALUE_KEYS}
    if len(pred) == 0:
        out["reason"] = "empty mesh"
        return out
    region = in_boxes(pred, boxes, settings.cube_margin_m)
    pred_cube = pred_cube[in_boxes(pred_cube, boxes, settings.cube_margin_m)]
    if len(gt_dynamic) == 0:
        out["cube_reason"] = "no ground-truth dynamic surface"
    else:
        out["cube_completion_ratio"] = float((nearest_distances(gt_dynamic, pred_cube) < thr).mean())
        if len(pred_cube):
            out["cube_accuracy_m"] = float(distance(pred_cube, "dynamic").mean())
        else:
            out["cube_reason"] = "no reconstructed surface inside the moving object's box"
    out["ghost_fraction"] = float((distance(pred, "all") > thr).mean())
    if len(observed_static):
        out["static_completion_ratio"] = float((nearest_distances(observed_static, pred) < thr).mean())
    else:
        out["static_reason"] = "no observed static surface (no GT poses or no valid static depth)"
    if (~region).any():
        out["static_accuracy_m"] = float(distance(pred[~region], "static").mean())
    return out


def region_submesh(
    mesh: trimesh.Trimesh, world_from_slam: np.ndarray, boxes: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], margin: float
) -> trimesh.Trimesh:
    """Faces of a SLAM-frame mesh with a vertex inside the dilated object boxes (still in the SLAM frame)."""
    if len(mesh.faces) == 0:
        return mesh
    near = in_boxes(transform(np.asarray(mesh.vertices, dtype=np.float64), world_from_slam), boxes, margin)
    keep = near[mesh.faces].any(1)
    return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)


def time_label(t: float) -> str:
    """Key prefix of a mesh time: ``mesh_t{t:.2f}``."""
    return f"mesh_t{t:.2f}"


def flatten_mesh_metrics(per_time: dict[float, dict[str, Any]], first: float, last: float) -> dict[str, Any]:
    """Per-time values -> flat keys ``mesh_t{t:.2f}_<name>`` plus ``<name>_first`` / ``<name>_last``
    summaries (unit suffix kept last: ``cube_accuracy_first_m``)."""
    out: dict[str, Any] = {}
    for t, values in per_time.items():
        for name, value in values.items():
            out[f"{time_label(t)}_{name}"] = value
    for label, t in (("first", first), ("last", last)):
        for name in MESH_VALUE_KEYS:
            stem, unit = (name[:-2], "_m") if name.endswith("_m") else (name, "")
            out[f"{stem}_{label}{unit}"] = per_time.get(t, {}).get(name)
    return out


def load_or_extract_meshes(
    run_dir: Path,
    times: Sequence[float],
    resolution: float,
    prefer_files: bool = True,
    culling: MeshConfig | None = MeshConfig(),
) -> tuple[dict[float, trimesh.Trimesh], str | None]:
    """Meshes of the run at ``times`` (SLAM frame).

    Uses run_dir/meshes/mesh_t{t:.3f}.ply where it exists (``prefer_files``), else extracts from
    run_dir/checkpoints/slam.pt at ``resolution``.

    Returns:
        {t: mesh} and a reason string when some mesh could not be had (else None).
    """
    meshes: dict[float, trimesh.Trimesh] = {}
    missing = []
    for t in times:
        path = RunDir(run_dir).mesh_path(t)
        if prefer_files and path.is_file():
            mesh = trimesh.load(path, force="mesh", process=False)
            meshes[t] = mesh if isinstance(mesh, trimesh.Trimesh) else trimesh.Trimesh()
        else:
            missing.append(t)
    if not missing:
        return meshes, None
    ckpt = RunDir(run_dir).checkpoint
    if not ckpt.is_file():
        return meshes, f"no mesh file and no checkpoint ({ckpt.name}) for t={missing}"
    field, meta = load_checkpoint(ckpt, device="cuda" if torch.cuda.is_available() else "cpu")
    for t in missing:
        tau = time_to_tau(t, meta["t0"], field.time_scale)
        meshes[t] = extract_mesh(field, tau, resolution, culling=culling, camera_centres=camera_centres(meta))
    return meshes, None


# --------------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------------


def dataset_view_from_run(run_dir: Path):
    """SequenceView of the dataset as configured for the run (run_dir/.hydra/config.yaml)."""
    from hydra.utils import instantiate

    from data_modules.sequence import SequenceView

    cfg_path = RunDir(run_dir).config
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{cfg_path}: run config not found (pass dataset_view= for runs without one)")
    cfg = OmegaConf.load(cfg_path)
    try:
        dataset = instantiate(cfg.dataset)
    except Exception as exc:  # Hydra wraps the reader's DatasetError
        cause = exc.__cause__ or exc
        raise ValueError(f"{cfg_path}: cannot build the dataset ({str(cause).splitlines()[0]})") from None
    data = OmegaConf.to_container(cfg.data, resolve=True) if "data" in cfg else {}
    return SequenceView(dataset, **data)


def evaluate_run(
    run_dir: str | Path,
    dataset_view=None,
    mesh_resolution: float = 0.02,
    times: Sequence[float] | None = None,
    frame: SlamFrame = "first_camera",
    settings: MeshEvalSettings = MeshEvalSettings(),
    prefer_mesh_files: bool = True,
    mesh_culling: MeshConfig | None = MeshConfig(),
) -> dict[str, Any]:
    """Flat, JSON-serialisable metrics of a run directory.

    Args:
        run_dir: holds trajectory.txt and checkpoints/slam.pt and/or meshes/*.ply.
        dataset_view: the SequenceView the run processed; default: rebuilt from run_dir/.hydra.
        mesh_resolution: marching-cubes step (m) for meshes extracted from the checkpoint.
        times: mesh times in seconds; default the first and last processed timestamps.
        frame: SLAM -> world transform for the mesh metrics, "first_camera" or "ate".
        settings: thresholds and sample counts.
        prefer_mesh_files: use run_dir/meshes/mesh_t{t:.3f}.ply when present.
        mesh_culling: for extracted meshes (``min_hits``, ``dynamic_window``, ``backfaces``).
    Returns:
        ATE keys (``ate_*``), and for datasets with GT geometry ``mesh_t{t:.2f}_<metric>`` per time plus
        ``<metric>_first`` / ``<metric>_last`` summaries; nulls come with a ``*_reason`` key.
    Raises:
        FileNotFoundError: no run dir (or no run config when ``dataset_view`` is None).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: run directory not found")
    view = dataset_view if dataset_view is not None else dataset_view_from_run(run_dir)
    dataset = getattr(view, "base", view)
    result: dict[str, Any] = {}

    ts_est = est = ate = None
    traj = run_dir / "trajectory.txt"
    if traj.is_file():
        ts_est, est_t = read_tum_trajectory(traj)
        est = est_t.numpy()
        ts_gt, gt = gt_trajectory(view)
        metrics, ate = trajectory_metrics(ts_est, est, ts_gt, gt)
        result.update(metrics)
    else:
        result.update(null_ate(f"{traj.name} not found"))

    if not has_gt_geometry(dataset):
        result["mesh_eval_reason"] = f"dataset {getattr(dataset, 'name', '?')} has no ground-truth geometry"
        return {k: jsonable(v) for k, v in result.items()}
    if times is None:
        stamps = None
        ckpt = RunDir(run_dir).checkpoint
        if ckpt.is_file():
            stamps = torch.load(ckpt, map_location="cpu", weights_only=True).get("timestamps")
        if not stamps and ts_est is not None:
            stamps = [float(t) for t in ts_est]
        if not stamps:
            result["mesh_eval_reason"] = "no processed timestamps (no checkpoint and no trajectory)"
            return {k: jsonable(v) for k, v in result.items()}
        times = [float(stamps[0]), float(stamps[-1])]
    times = list(dict.fromkeys(float(t) for t in times))  # unique, in order

    # SLAM -> world.
    if frame == "ate":
        if ate is None:
            result["mesh_eval_reason"] = "frame=ate needs a computable ATE"
            return {k: jsonable(v) for k, v in result.items()}
        world_from_slam = ate.alignment_matrix
    elif frame == "first_camera":
        if not getattr(view, "has_gt_poses", False):
            result["mesh_eval_reason"] = "no ground-truth pose for the first processed frame"
            return {k: jsonable(v) for k, v in result.items()}
        first = int(getattr(view, "source_indices", [0])[0])
        world_from_slam = np.asarray(torch.as_tensor(dataset.camera_pose(first), dtype=torch.float64))
    else:
        raise ValueError(f"frame must be 'first_camera' or 'ate', got {frame!r}")

    meshes, reason = load_or_extract_meshes(run_dir, times, mesh_resolution, prefer_mesh_files, mesh_culling)
    if reason is not None:
        result["mesh_eval_reason"] = reason
    s = settings
    observed = observed_static_surface(view, s.static_every, s.static_per_frame, s.seed)
    per_time: dict[float, dict[str, Any]] = {}
    for t, mesh in meshes.items():
        boxes = object_boxes(dataset, t)
        pred = transform(sample_mesh_surface(mesh, s.pred_samples, seed=s.seed), world_from_slam)
        pred_cube = transform(
            sample_mesh_surface(region_submesh(mesh, world_from_slam, boxes, s.cube_margin_m), s.dynamic_samples, seed=s.seed),
            world_from_slam,
        )
        gt_dynamic = np.asarray(dataset.sample_surface(t, s.dynamic_samples, part="dynamic", seed=s.seed + 2))
        distance = gt_distance_fn(dataset, t, s)
        per_time[t] = mesh_time_metrics(pred, pred_cube, gt_dynamic, observed, boxes, distance, s)
    result.update(flatten_mesh_metrics(per_time, times[0], times[-1]))
    result["mesh_eval_frame"] = frame
    result["mesh_eval_threshold_m"] = s.threshold_m
    return {k: jsonable(v) for k, v in result.items()}
