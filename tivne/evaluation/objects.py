"""Per-object trajectory error of a run's objects/<id>.txt against the dataset's GT object poses.

GT object trajectories come from the synthetic family (``object_poses(t)``) and the Co-Fusion
layout (``trajectories/gt-<name>-<id>.txt``, ``object_trajectories``). Each GT object is matched to
the written track that follows it: among the tracks whose origin stays within ``MATCH_DISTANCE_M``
of the GT object's centre (mean over their common frames, in the GT world; beyond the object's
bounding sphere where the dataset knows its extent: a track's origin is the centre of the points it
first saw, on the seen side of a large object), the one with the most poses. So a run with geometric
masks (its own ids) is scored like one with dataset ids.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from data_modules.poses import interpolate_poses
from data_modules.sequence import SequenceView
from data_modules.tables import read_tum_trajectory
from tivne.evaluation.ground_truth import ground_truth_of, object_box
from tivne.metrics.objects import object_trajectory_error
from tivne.slam.outputs import RunDir

MATCH_DISTANCE_M = 0.3
GT_TIME_TOLERANCE_S = 1e-3


def gt_object_trajectories(view: SequenceView) -> dict[str, tuple[np.ndarray, torch.Tensor]]:
    """{object name: (timestamps (M,), object-to-world poses (M, 4, 4) float64)} of the dataset's
    moving objects over the view's frames ({} when it ships none)."""
    base = view.base
    if hasattr(base, "object_poses") and getattr(base, "object_names", None):
        stamps = np.asarray(view.timestamps, dtype=np.float64)
        per_time = [base.object_poses(float(t)) for t in stamps]
        return {n: (stamps, torch.stack([p[n] for p in per_time]).double()) for n in base.object_names}
    trajectories = getattr(base, "object_trajectories", None)
    if trajectories and hasattr(base, "frame_numbers"):  # Co-Fusion: keyed by frame number
        when = {int(num): float(base.timestamps[i]) for i, num in enumerate(base.frame_numbers)}
        out = {}
        for name, (frames, poses) in trajectories.items():
            keep = [i for i, f in enumerate(frames) if int(f) in when]
            if keep:
                out[name] = (np.asarray([when[int(frames[i])] for i in keep]), poses[keep].double())
        return out
    return {}


def _gt_at(gt: tuple[np.ndarray, torch.Tensor], stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GT poses (K, 4, 4) at the ``stamps`` the GT covers, and the (N,) bool of which those are."""
    poses, valid = interpolate_poses(gt[0], gt[1], stamps, tolerance=GT_TIME_TOLERANCE_S)
    return poses.numpy()[valid], valid


def match_reach(view: SequenceView, name: str, t: float) -> float:
    """Metres a track's origin may stay from GT object ``name``'s centre and still follow it:
    ``MATCH_DISTANCE_M`` beyond the object's bounding sphere at time ``t`` where the dataset has its
    box (the synthetic family), else ``MATCH_DISTANCE_M``."""
    gt = ground_truth_of(view)
    return MATCH_DISTANCE_M + (float(np.linalg.norm(object_box(gt, t, name).half_extents)) if gt is not None else 0.0)


def match_tracks(tracks: dict[int, tuple[np.ndarray, torch.Tensor]], gt: dict[str, tuple[np.ndarray, torch.Tensor]],
                 world: np.ndarray, reach: dict[str, float]) -> dict[str, int]:
    """{GT name: track id} (see the module docstring); a track serves one GT object at most.
    reach: per GT name, how far (m) a track's origin may stay from its centre (:func:`match_reach`)."""
    candidates = []
    for name, traj in gt.items():
        for k, (stamps, poses) in tracks.items():
            g, valid = _gt_at(traj, stamps)
            if not valid.any():
                continue
            origin = (world[None] @ poses.numpy()[valid])[:, :3, 3]
            d = float(np.linalg.norm(origin - g[:, :3, 3], axis=1).mean())
            if d <= reach[name]:
                candidates.append((-int(valid.sum()), d, name, k))
    out, used = {}, set()
    for _, _, name, k in sorted(candidates):
        if name not in out and k not in used:
            out[name] = k
            used.add(k)
    return out


def object_section(run: RunDir, view: SequenceView, world: np.ndarray | None) -> dict[str, Any]:
    """metrics.json keys ``object_<name>_ate_m`` / ``_rot_deg`` (and ``_ate_max_m``, ``_rot_max_deg``,
    ``_poses``, ``_track``) per GT object, ``objects_tracked``, ``object_ate_max_m`` and
    ``object_rot_max_deg`` (the worst object); {} for a run without objects/."""
    paths = run.object_paths()
    if not paths:
        return {}
    tracks = {k: read_tum_trajectory(p, what="object trajectory") for k, p in paths.items()}
    out: dict[str, Any] = {"objects_tracked": len(tracks)}
    gt = gt_object_trajectories(view)
    if not gt:
        return out | {"object_eval_reason": f"dataset {view.name} has no ground-truth object trajectories"}
    if world is None:
        return out | {"object_eval_reason": "no SLAM-to-world alignment (no ground-truth camera pose)"}
    matched = match_tracks(tracks, gt, world, {name: match_reach(view, name, float(traj[0][0])) for name, traj in gt.items()})
    worst_t, worst_r = [], []
    for name in gt:
        if name not in matched:
            out[f"object_{name}_ate_m"] = out[f"object_{name}_rot_deg"] = None
            out[f"object_{name}_reason"] = "no written track follows it"
            continue
        stamps, poses = tracks[matched[name]]
        g, valid = _gt_at(gt[name], stamps)
        err = object_trajectory_error(poses.numpy()[valid], g, world)
        out |= err.as_metrics(name) | {f"object_{name}_track": matched[name]}
        worst_t.append(err.ate_rmse_m)
        worst_r.append(err.rot_rmse_deg)
    out["object_ate_max_m"] = max(worst_t) if worst_t else None
    out["object_rot_max_deg"] = max(worst_r) if worst_r else None
    return out
