"""Pose-graph edges from the dense odometry: which keyframes to align a new one to, the alignment,
and the tests an edge must pass before it enters the graph.

* co-visible edges: the predecessor and the ``covisible`` earlier keyframes (among the recent
  ``loop_min_gap``) that the new keyframe's pixels reproject into most;
* loop closures: keyframes at least ``loop_min_gap`` keyframes older, close in pose (distance and
  viewing angle) and overlapping in view, verified by the odometry from a wider basin (more
  pyramid levels, more iterations).

Every pyramid is built with the keyframe's current dynamic mask, so masked (moving) pixels never
enter an edge.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from tivne.config import BackendConfig, OdometryConfig
from tivne.geometry import invert_pose, pose_difference
from tivne.render.rays import View
from tivne.slam.tracking.odometry import OdometryResult, frame_pyramid, track_pyramids
from tivne.slam.tracking.overlap import view_overlaps, views_seeing
from tivne.slam.tracking.pyramid import PyramidLevel
from tivne.slam.tracking.sensor import Shutter


def covisible_candidates(views: list[View], new: View, K: torch.Tensor, cfg: BackendConfig) -> list[int]:
    """Indices into ``views`` (the keyframes before ``new``, oldest first) to align ``new`` to: the
    predecessor always, plus up to ``cfg.covisible`` of the recent ones with the largest overlap."""
    if not views:
        return []
    recent = list(range(max(0, len(views) - cfg.loop_min_gap), len(views) - 1))
    ratios = view_overlaps(new, [views[i].pose for i in recent], K)
    ranked = [recent[i] for i in torch.argsort(ratios, descending=True).tolist() if ratios[i] >= cfg.min_overlap]
    return sorted(ranked[: cfg.covisible]) + [len(views) - 1]


def loop_candidates(views: list[View], new: View, K: torch.Tensor, cfg: BackendConfig) -> list[int]:
    """Indices into ``views`` of old keyframes (``loop_min_gap`` or more keyframes back) near ``new``
    in pose and overlapping its view, the most overlapping first, at most ``cfg.loop_candidates``."""
    old = views[: max(0, len(views) - cfg.loop_min_gap)]
    seeing = views_seeing(new, [v.pose for v in old], K, cfg.loop_max_distance_m, cfg.loop_max_angle_deg, cfg.min_overlap)
    return [i for i, _ in sorted(seeing, key=lambda item: -item[1])][: cfg.loop_candidates]


@dataclass(frozen=True)
class Alignment:
    """A dense alignment of keyframe ``cur`` to keyframe ``ref`` (frame ids), its odometry result,
    whether it passed the edge tests and, if not, why."""

    ref: int
    cur: int
    result: OdometryResult
    accepted: bool
    reason: str


def wide_config(odometry: OdometryConfig, cfg: BackendConfig) -> OdometryConfig:
    """The loop-closure verification's odometry: ``loop_extra_levels`` more levels, twice the iterations."""
    return dataclasses.replace(odometry, levels=odometry.levels + cfg.loop_extra_levels, max_iterations=2 * odometry.max_iterations)


def keyframe_pyramid(view: View, K: torch.Tensor, odometry: OdometryConfig, cfg: BackendConfig) -> list[PyramidLevel]:
    """The keyframe's pyramid (with the wide basin's levels), its current dynamic mask excluded."""
    return frame_pyramid(view.colour(), view.depth, K, wide_config(odometry, cfg), view.dynamic)


def align(
    ref: View, cur: View, ref_pyr: list[PyramidLevel], cur_pyr: list[PyramidLevel], odometry: OdometryConfig,
    cfg: BackendConfig, loop: bool, shutters: tuple[Shutter | None, ...] = (),
) -> Alignment:
    """Align ``cur`` to ``ref`` from their current relative pose (``shutters``: their rolling shutters,
    ``cur``'s first, as :func:`track_pyramids` takes them; () = global), then test the edge: the odometry's
    own checks (converged, overlap, pose σ), an inlier ratio of at least ``cfg.min_inlier_ratio``,
    and consistency with the current estimate (the chain): within ``max_edge_m`` / ``max_edge_deg``
    of it, or ``loop_max_correction_m`` / ``_deg`` for a loop closure (drift is what it corrects)."""
    T_init = invert_pose(ref.pose.double()) @ cur.pose.double()
    result = track_pyramids(ref_pyr, cur_pyr, T_init, wide_config(odometry, cfg) if loop else odometry, shutters=shutters)
    metres, degrees = pose_difference(T_init, result.T_ref_cur)
    max_m, max_deg = (cfg.loop_max_correction_m, cfg.loop_max_correction_deg) if loop else (cfg.max_edge_m, cfg.max_edge_deg)
    reason = ""
    if not result.ok:
        reason = f"odometry failed (inliers {result.inlier_ratio:.2f}, overlap {result.overlap:.2f}, converged {result.converged})"
    elif result.inlier_ratio < cfg.min_inlier_ratio:
        reason = f"inlier ratio {result.inlier_ratio:.2f} < {cfg.min_inlier_ratio}"
    elif metres > max_m or degrees > max_deg:
        reason = f"inconsistent with the chain ({100 * metres:.1f} cm, {degrees:.2f} deg)"
    return Alignment(ref.frame_id, cur.frame_id, result, not reason, reason)
