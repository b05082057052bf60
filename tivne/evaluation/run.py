"""A run directory against its sequence: trajectory, re-rendered images and 4D meshes.

:func:`evaluate_run` is the library entry point (``tivne.train``'s final evaluation and the
``tivne.evaluate`` command both call it); it reads the run through :class:`tivne.slam.outputs.RunDir`
and the dataset through :class:`tivne.evaluation.ground_truth.GroundTruth`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import trimesh

from data_modules.frame import DatasetError
from data_modules.sequence import SequenceDataset, SequenceView
from data_modules.tables import read_tum_trajectory
from tivne.config import ConfigError, MeshConfig, MeshEvalSettings, RenderConfig
from tivne.evaluation.ground_truth import GroundTruth, as_view, ground_truth_of
from tivne.evaluation.images import image_metrics, null_images, render_frames
from tivne.evaluation.objects import object_section
from tivne.evaluation.surfaces import flatten_mesh_metrics, mesh_time_metrics
from tivne.field.networks import TimeVaryingField
from tivne.meshing import TIME_TOLERANCE_S, mesh_at, select_mesh_times
from tivne.metrics.trajectory import ATEResult, ate_from_trajectories
from tivne.slam.checkpoint import camera_centres, load_checkpoint
from tivne.slam.outputs import RunDir, jsonable

ATE_KEYS = ("ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_std_m", "ate_max_m")
SlamFrame = Literal["first_camera", "ate"]


@dataclass
class RunRecord:
    """What a run directory holds: the trajectory (timestamps (N,), c2w poses (N, 4, 4) float64, or
    None) and the checkpoint (field and meta, or None)."""

    run: RunDir
    timestamps: np.ndarray | None
    poses: np.ndarray | None
    field: TimeVaryingField | None
    meta: dict[str, Any] | None

    @classmethod
    def read(cls, run_dir: str | Path, device: str) -> "RunRecord":
        run = RunDir(run_dir)
        if not run.root.is_dir():
            raise FileNotFoundError(f"{run.root}: run directory not found")
        ts = poses = field = meta = None
        if run.trajectory.is_file():
            ts, poses_t = read_tum_trajectory(run.trajectory)
            ts, poses = np.asarray(ts, dtype=np.float64), poses_t.numpy()
        if run.checkpoint.is_file():
            field, meta = load_checkpoint(run.checkpoint, device=device)
        return cls(run, ts, poses, field, meta)

    @property
    def recorded_times(self) -> list[float]:
        """Timestamps of the processed frames (the checkpoint's, else the trajectory's; [] without either)."""
        if self.meta is not None and self.meta.get("timestamps"):
            return [float(t) for t in self.meta["timestamps"]]
        return [] if self.timestamps is None else [float(t) for t in self.timestamps]


# --------------------------------------------------------------------------------------------------
# Trajectory
# --------------------------------------------------------------------------------------------------


def gt_trajectory(view: SequenceView) -> tuple[np.ndarray, np.ndarray]:
    """GT camera poses of the view's frames that have one: timestamps (K,) s, poses (K, 4, 4) float64 c2w."""
    ts, poses = [], []
    if view.has_gt_poses:
        for i, src in enumerate(view.source_indices):
            try:
                pose = view.base.camera_pose(int(src))
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
) -> tuple[dict[str, Any], ATEResult | None]:
    """ATE (SE(3)-aligned, associated by timestamp) as metrics.json keys.

    Args:
        ts_est: (N,), est_poses: (N, 4, 4); ts_gt: (M,), gt_poses: (M, 4, 4).
    Returns:
        ({ate_rmse_m, ..., ate_frames} or nulls with ``ate_reason``) and the ATEResult (None when
        not computable).
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


def trajectory_section(record: RunRecord, view: SequenceView) -> tuple[dict[str, Any], ATEResult | None]:
    """ATE keys plus ``sequence_frames`` and ``ate_partial``: True when the run stopped early (a
    trajectory shorter than the sequence, or metrics.json says ``complete: false``), so the ATE is
    over the frames it reached only."""
    if record.timestamps is None:
        return {**null_ate(f"{RunDir.TRAJECTORY} not found"), "sequence_frames": len(view)}, None
    out, ate = trajectory_metrics(record.timestamps, record.poses, *gt_trajectory(view))
    interrupted = record.run.read_metrics().get("complete") is False
    out["sequence_frames"] = len(view)
    out["ate_partial"] = bool(len(record.timestamps) < len(view) or interrupted)
    return out, ate


def image_section(record: RunRecord, view: SequenceView, render: RenderConfig, settings: MeshEvalSettings) -> dict[str, Any]:
    """PSNR / SSIM / ... of every ``settings.render_every``-th processed frame re-rendered from the
    checkpoint (:mod:`tivne.evaluation.images`); needs no ground truth."""
    if settings.render_every == 0:
        return {"psnr_reason": "settings.render_every=0"}
    if record.field is None:
        return null_images(f"no checkpoint ({RunDir.CHECKPOINT})")
    frames = render_frames(record.field, record.meta, view, render, settings.render_every, settings.render_stride)
    return image_metrics(frames)


# --------------------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------------------


def world_from_slam(frame: SlamFrame, view: SequenceView, ate: ATEResult | None) -> tuple[np.ndarray | None, str | None]:
    """(4, 4) map from the SLAM frame to the dataset's world frame, or (None, reason).

    ``first_camera``: the SLAM frame is the first camera's, so the map is that frame's GT pose (the
    mesh error then includes the drift of the frames that built it). ``ate``: the SE(3) alignment of
    the ATE (spreads the trajectory error; more robust to a bad first pose).
    """
    if frame == "ate":
        return (None, "frame=ate needs a computable ATE") if ate is None else (ate.alignment_matrix, None)
    try:
        pose = view.base.camera_pose(int(view.source_indices[0])) if view.has_gt_poses else None
    except DatasetError:
        pose = None
    if pose is None:
        return None, "no ground-truth pose for the first processed frame"
    return np.asarray(torch.as_tensor(pose, dtype=torch.float64)), None


def run_meshes(
    record: RunRecord, times: list[float], mesh: MeshConfig, prefer_files: bool = True
) -> tuple[dict[float, trimesh.Trimesh], str | None]:
    """The run's meshes at ``times`` (SLAM frame): run_dir/meshes/mesh_t{t:.3f}.ply where it exists
    (``prefer_files``), else extracted from the checkpoint with ``mesh``'s resolution and culling.

    Returns:
        {t: mesh} and a reason when some time has neither a file nor a checkpoint (else None).
    """
    meshes: dict[float, trimesh.Trimesh] = {}
    cache: dict = {}
    for t in times:
        path = record.run.mesh_path(t)
        if prefer_files and path.is_file():
            loaded = trimesh.load(path, force="mesh", process=False)
            meshes[t] = loaded if isinstance(loaded, trimesh.Trimesh) else trimesh.Trimesh()
        elif record.field is not None:
            tau = record.meta["clock"].tau(t)
            meshes[t] = mesh_at(record.field, tau, mesh, camera_centres(record.meta), cache, record.meta["depth_views"])
    missing = [t for t in times if t not in meshes]
    reason = f"no mesh file and no checkpoint ({RunDir.CHECKPOINT}) for t={missing}" if missing else None
    return meshes, reason


def mesh_section(
    record: RunRecord,
    gt: GroundTruth,
    times: list[float],
    to_world: np.ndarray,
    mesh: MeshConfig,
    settings: MeshEvalSettings,
    prefer_files: bool,
) -> dict[str, Any]:
    """The 4D mesh metrics at ``times`` (see :mod:`tivne.evaluation.surfaces`) as flat keys."""
    meshes, reason = run_meshes(record, times, mesh, prefer_files)
    recorded = record.recorded_times
    span = (recorded[0], recorded[-1])
    per_time = {}
    for t, slam_mesh in meshes.items():
        world = slam_mesh.copy()
        world.apply_transform(to_world)
        per_time[t] = mesh_time_metrics(gt, t, world, span, settings)

    def evaluated(reference: float) -> float | None:
        return next((t for t in per_time if abs(t - reference) <= TIME_TOLERANCE_S), None)

    out = flatten_mesh_metrics(per_time, list(gt.object_names), evaluated(span[0]), evaluated(span[1]))
    if reason is not None:
        out["mesh_eval_reason"] = reason
    return out


# --------------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------------


def evaluate_run(
    run_dir: str | Path,
    dataset: SequenceDataset,
    mesh: MeshConfig = MeshConfig(),
    settings: MeshEvalSettings = MeshEvalSettings(),
    render: RenderConfig = RenderConfig(),
    frame: SlamFrame = "first_camera",
    prefer_mesh_files: bool = True,
    device: str | None = None,
) -> dict[str, Any]:
    """Flat, JSON-serialisable metrics of a run directory against its sequence.

    Args:
        run_dir: holds trajectory.txt and/or checkpoints/slam.pt and/or meshes/*.ply.
        dataset: the sequence the run processed (a :class:`SequenceView` as the run streamed it, or
            a dataset taken whole); mesh metrics need it to be a :class:`GroundTruth`.
        mesh: ``times`` to evaluate (empty: the first and last processed frame; each must lie in the
            recorded range), ``resolution`` and culling for meshes extracted from the checkpoint.
        settings: thresholds, windows and sample counts.
        render: sample placement for re-rendering frames (the run's own ``render`` section).
        frame: SLAM -> world map for the mesh metrics, "first_camera" or "ate".
        prefer_mesh_files: use run_dir/meshes/mesh_t{t:.3f}.ply when present.
        device: where to load the field (default cuda when available).
    Returns:
        ATE keys (``ate_*``, ``ate_partial``, ``sequence_frames``), image keys (``psnr_db``, ``ssim``,
        ...), per-object trajectory keys (``object_<name>_ate_m``, ``object_<name>_rot_deg``, ...,
        :func:`tivne.evaluation.objects.object_section`) for a run with objects/, and for a
        :class:`GroundTruth` dataset the 4D mesh keys ``mesh_t{t:.2f}_*`` and their
        summaries; nulls come with a ``*_reason`` key.
    Raises:
        FileNotFoundError: no run dir. ConfigError: a mesh time outside the recorded range (checked
        before anything is computed, so nothing gets merged).
    """
    if frame not in ("first_camera", "ate"):
        raise ConfigError(f"frame={frame!r}: must be one of 'first_camera', 'ate'")
    record = RunRecord.read(run_dir, device or ("cuda" if torch.cuda.is_available() else "cpu"))
    recorded = record.recorded_times
    times = select_mesh_times(recorded, list(mesh.times) or None) if recorded or mesh.times else []
    view = as_view(dataset)
    result, ate = trajectory_section(record, view)
    result.update(image_section(record, view, render, settings))
    gt = ground_truth_of(view)
    to_world, reason = world_from_slam(frame, view, ate)
    result.update(object_section(record.run, view, to_world))
    if gt is None:
        reason = f"dataset {view.name} has no ground-truth geometry"
    elif not times:
        reason = "no processed timestamps (no checkpoint and no trajectory)"
    if reason is not None:
        result["mesh_eval_reason"] = reason
    else:
        result.update(mesh_section(record, gt, times, to_world, mesh, settings, prefer_mesh_files))
        result.update(mesh_eval_frame=frame, mesh_eval_threshold_m=settings.threshold_m, mesh_eval_window_s=settings.window_s,
                      mesh_eval_times=[round(t, 6) for t in times])
    return {k: jsonable(v) for k, v in result.items()}
