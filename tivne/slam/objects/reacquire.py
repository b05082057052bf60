"""Taking up a known object again after it was out of sight: its pose from several rotation hypotheses.

While an object is unseen it may turn by anything (a box spinning in place, seen again a second
later), so the constant-velocity prediction's rotation is a guess and Gauss–Newton from it lands in
the wrong basin as often as not. Its position is known well enough (the prediction moved onto the
centre of what is seen now), so :func:`rotation_hypotheses` turns the prediction about that centre
in steps about three axes, each hypothesis is aligned at the coarsest pyramid level against the
stored view that saw the object from the hypothesised side, and :func:`ranked_alignments` orders
those that explain the pixels best. The caller refines the first few at every level and keeps the
best of those: the coarsest level prunes, the finest level's texture decides (a ball's or a
cylinder's turns fit its geometry alike; only the texture tells them apart, and at the coarsest
level it is a blur).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import torch

from data_modules.poses import rotation_from_vector, rotation_vector
from tivne.slam.tracking.odometry import OdometryResult


@dataclass(frozen=True)
class Hypothesis:
    """One candidate object-to-world pose (4, 4) float64 and its coarse alignment (None: not run)."""

    T_wo: torch.Tensor
    result: OdometryResult | None = None


def rotation_hypotheses(T_wo: torch.Tensor, axes: torch.Tensor, step_deg: float) -> list[torch.Tensor]:
    """Object-to-world poses (4, 4) float64: ``T_wo`` itself, then turned about its own origin by every
    multiple of ``step_deg`` (short of a full turn) about each of the world ``axes`` (A, 3).

    The origin (the object's centre, as its track defines it) stays where it is: R' = R_h · R, t' = t.
    """
    out = [T_wo.double().clone()]
    steps = max(1, int(round(360.0 / step_deg)))
    for axis in axes.double():
        axis = axis / axis.norm().clamp_min(1e-12)
        for k in range(1, steps):
            T = T_wo.double().clone()
            T[:3, :3] = rotation_from_vector(axis * math.radians(k * 360.0 / steps)) @ T[:3, :3]
            out.append(T)
    return out


def ranked_alignments(candidates: list[Hypothesis], min_share: float = 0.8) -> list[Hypothesis]:
    """The hypotheses that explain the pixels best, best first: the alignments whose overlap ×
    inlier ratio reaches ``min_share`` of the best one's, by photometric RMS (the texture tells
    apart what geometry cannot, e.g. a box turned by 180°); without colour, by overlap × inlier
    ratio. Empty when no alignment ran."""
    done = [h for h in candidates if h.result is not None and h.result.num_valid > 0]
    if not done:
        return []
    support = [h.result.overlap * h.result.inlier_ratio for h in done]
    top = max(support)
    close = [(h, s) for h, s in zip(done, support) if s >= min_share * top]
    if all(math.isnan(h.result.rms_photometric) for h, _ in close):
        return [h for h, _ in sorted(close, key=lambda hs: -hs[1])]
    return [h for h, _ in sorted(close, key=lambda hs: hs[0].result.rms_photometric if not math.isnan(hs[0].result.rms_photometric) else math.inf)]


def best_alignment(candidates: list[Hypothesis], min_share: float = 0.8) -> Hypothesis | None:
    """The first of :func:`ranked_alignments`, or None when no alignment ran."""
    ranked = ranked_alignments(candidates, min_share)
    return ranked[0] if ranked else None


def spin_axis(taus: list[float], poses: torch.Tensor, baseline: float, min_deg: float) -> torch.Tensor | None:
    """(3,) world axis a track (increasing ``taus``, (N, 4, 4) ``poses``) turned about over its last
    ``baseline`` of observations, or None when it turned by less than ``min_deg`` there: a spinning
    object most likely went on spinning about the same axis while unseen."""
    inner = bisect.bisect_left(taus, taus[-1] - baseline)
    if inner >= len(taus) - 1:
        return None
    w = rotation_vector(poses[-1, :3, :3].double() @ poses[inner, :3, :3].double().T)
    return w / w.norm() if float(w.norm()) >= math.radians(min_deg) else None
