"""A finished run (or its checkpoint) as a recording: ``python -m tivne.view`` (:func:`record_run`).

On the ``frame`` / ``scene_time`` timelines: every processed frame's camera (trajectory.txt) and its
GT camera, the estimated and GT trajectories growing as line strips, the per-frame translation error
against GT (SE(3)-aligned, as the ATE; :mod:`tivne.reporting.trajectory`) as a plot, every moving
object's GT box, and the 4D mesh sequence: the field meshed (:mod:`tivne.meshing`: the static scene
and the moving parts at that time) at every ``every``-th processed frame (or ``mesh.times``), so
scrubbing the slider shows the scene as it was. The observed colour and depth at the mesh frames too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_modules.sequence import SequenceView
from tivne.config import MeshConfig, ViewerConfig
from tivne.evaluation.ground_truth import ground_truth_of
from tivne.evaluation.run import RunRecord, gt_trajectory
from tivne.meshing import mesh_at, select_mesh_times
from tivne.reporting.trajectory import trajectory_errors
from tivne.slam.checkpoint import camera_centres
from tivne.slam.outputs import RunDir
from tivne.viewer import entities as E
from tivne.viewer.recorder import open_stream, to_uint8

VIEW_RECORDING = "view.rrd"


@dataclass(frozen=True)
class ViewSummary:
    """What :func:`record_run` wrote: the file (None for a live sink), frames, (time s, faces) per
    mesh, frames with a GT error, and why there is no GT part (None when there is)."""

    path: Path | None
    frames: int
    meshes: list[tuple[float, int]]
    error_frames: int
    gt_reason: str | None


def gt_in_slam_frame(ts: np.ndarray, poses: np.ndarray, gt_ts: np.ndarray, gt_poses: np.ndarray, max_diff: float = 0.02):
    """(4, 4) map from the GT world to the SLAM frame, tied at the first estimated frame with a GT
    pose within ``max_diff`` s (est @ gt⁻¹ there), or None when no frame has one."""
    for t, pose in zip(ts, poses):
        if len(gt_ts) == 0:
            break
        j = int(np.argmin(np.abs(gt_ts - t)))
        if abs(gt_ts[j] - t) <= max_diff:
            return pose @ np.linalg.inv(gt_poses[j])
    return None


def record_run(
    run_dir: str | Path,
    view: SequenceView | None,
    every: int | None = 10,
    mesh: MeshConfig = MeshConfig(),
    cfg: ViewerConfig = ViewerConfig(kind="rerun"),
    out: str | Path | None = None,
    device: str = "cpu",
    until: float | None = None,
) -> ViewSummary:
    """Write the recording of a run (see the module docstring) to ``out`` (default run_dir/view.rrd)
    or ``cfg.sink``; ``view``: the run's sequence (None: no GT, no images); ``until``: only the
    frames up to this many seconds after the first, and the viewer opens at the last of them.

    Raises:
        FileNotFoundError: no run dir or no trajectory.txt; ConfigError: bad mesh times.
    """
    record = RunRecord.read(run_dir, device)
    if record.timestamps is None:
        raise FileNotFoundError(f"{RunDir(run_dir).trajectory}: not found; the run has no poses to view")
    ts, poses = record.timestamps, record.poses
    if until is not None:  # a recording of the first part, e.g. to open a viewer at a chosen time
        keep = ts - ts[0] <= until + 1e-6
        ts, poses = ts[keep], poses[keep]
    times = select_mesh_times(record.recorded_times, list(mesh.times) or None, every) if record.field is not None else []
    times = [t for t in times if t <= ts[-1] + 1e-6]
    path = Path(out) if out is not None else Path(run_dir) / VIEW_RECORDING
    rec = open_stream(cfg, path, recording_id=str(Path(run_dir).resolve()), rendered=False,
                      play_state="paused" if until is None else "following")
    E.log_run_info(rec, float(ts[0]), None if view is None else np.asarray(view.intrinsics.K(), dtype=np.float32),
                   *((view.intrinsics.width, view.intrinsics.height) if view is not None else (0, 0)))
    gt_ts, gt_poses = gt_trajectory(view) if view is not None else (np.zeros(0), np.zeros((0, 4, 4)))
    to_slam = gt_in_slam_frame(ts, poses, gt_ts, gt_poses)
    reason = None if to_slam is not None else ("no sequence" if view is None else "no ground-truth pose at the run's frames")
    errors = _log_errors(rec, ts, poses, gt_ts, gt_poses)
    mesh_frames = {E.nearest_frame(ts, t): t for t in times}
    _log_frames(rec, ts, poses, gt_ts, gt_poses, to_slam, view, set(mesh_frames), cfg.trajectory_every)
    written, cache = [], {}  # mesh_at: with field=objects the static field and each object meshed once, objects placed per time
    for i, t in sorted(mesh_frames.items()):
        m = mesh_at(record.field, record.meta["clock"].tau(t), mesh, camera_centres=camera_centres(record.meta), cache=cache,
                        depth_views=record.meta["depth_views"])
        E.set_time(rec, i, t - float(ts[0]))
        E.log_mesh(rec, m)
        written.append((float(t), int(len(m.faces))))
    rec.flush()
    rec.disconnect()
    return ViewSummary(path if cfg.sink == "file" else None, len(ts), written, errors, reason)


def _log_errors(rec, ts: np.ndarray, poses: np.ndarray, gt_ts: np.ndarray, gt_poses: np.ndarray) -> int:
    """The per-frame translation error (m) against GT as a plot; returns how many frames have one."""
    errors, _ = trajectory_errors(ts, poses, gt_ts, gt_poses) if len(gt_ts) else (None, None)
    if errors is None:
        return 0
    rr = E.rerun()
    for t, e in zip(errors.times, errors.translation_m):
        E.set_time(rec, E.nearest_frame(ts - ts[0], t), float(t))
        rec.log(E.ERROR, rr.Scalars(float(e)))
    return len(errors.times)


def _log_frames(rec, ts, poses, gt_ts, gt_poses, to_slam, view: SequenceView | None, image_frames: set[int], strip_every: int) -> None:
    """Cameras, trajectories, GT boxes of the moving objects and the colour at ``image_frames``."""
    rr = E.rerun()
    gt = ground_truth_of(view) if view is not None and to_slam is not None else None
    gt_path = [] if to_slam is None else [(to_slam @ p)[:3, 3] for p in gt_poses]
    for i, (t, pose) in enumerate(zip(ts, poses)):
        E.set_time(rec, i, float(t - ts[0]))
        E.log_pose(rec, E.CAMERA, pose)
        if to_slam is not None and len(gt_ts):
            j = int(np.argmin(np.abs(gt_ts - t)))
            if abs(gt_ts[j] - t) <= 0.02:
                E.log_pose(rec, E.GT_CAMERA, to_slam @ gt_poses[j])
        if i % strip_every == 0 or i == len(ts) - 1:
            E.log_strip(rec, E.TRAJECTORY, poses[: i + 1, :3, 3], E.ESTIMATE_COLOUR)
            E.log_strip(rec, E.GT_TRAJECTORY, [p for p, s in zip(gt_path, gt_ts) if s <= t + 1e-6], E.GT_COLOUR)
        for name in [] if gt is None else gt.object_names:
            center, half, R = (np.asarray(x, dtype=np.float64) for x in gt.dynamic_box(float(t), name))
            box = np.eye(4)
            box[:3, :3], box[:3, 3] = R, center
            E.log_box(rec, f"{E.GT_OBJECTS}/{name}", to_slam @ box, half, E.GT_COLOUR)
        if view is not None and i in image_frames and i < len(view):
            frame = view[i]
            rec.log(E.RGB, rr.Image(to_uint8(frame.rgb)))
            rec.log(E.DEPTH, rr.DepthImage(frame.depth.numpy().astype(np.float32), meter=1.0))
