"""Loop closure along an object's chain of reference views.

An object's pose is measured against its stored views (:mod:`tivne.slam.objects.references`); each new
view's pose comes from an older one, so the views form a chain whose error grows with every link (a
symmetric object's spin is held by its texture alone, ~0.1° a link). When a turning object shows a side
again that a view far back in the chain saw, the tracker aligns to that older view and the pose jumps
back by the drift, while the views in between keep it: the next turn repeats the same error.

Here that moment is a loop closure. The view is aligned both to the old view and to the view the chain
reached (each alone, without the motion prior, which would pull both to the prediction); their
disagreement L (object frame: C_old = L · C_chain, C camera-to-object) is the chain's drift. It is
spread over the chain as a one-loop pose graph with equal links spreads it: a view stored a fraction w
of the way along the chain (in field time, from the old view to the reached one) turns by L^w, later
ones by all of L, and so do the track's poses (T_wo ← T_wo · L^-w). Not drift, and ignored: a
disagreement larger than a chain drifts (``LOOP_MAX_DEG``, ``LOOP_MAX_SHIFT_M``), one from alignments
that fit worse than the object's usually do (``LOOP_FIT_RATIO``: a blurred view, another side), and one
the object's next view does not repeat (:class:`ChainLoops`: a lock onto smeared texture differs from
frame to frame, drift does not). The tracker's counters (metrics.json): ``object_loops_closed``,
``object_loops_refused``, ``object_loop_largest_deg``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from tivne.config import OdometryConfig
from tivne.geometry import invert_pose, pose_difference, rotation_angle_deg, transform_points
from tivne.slam.objects.motion import interpolate_se3, odometry_init
from tivne.slam.objects.references import Reference
from tivne.slam.objects.track import ObjectTrack
from tivne.slam.tracking.odometry import OdometryResult, track_pyramids
from tivne.slam.tracking.pyramid import PyramidLevel

# Stored views between the old view and the one the chain reached for their disagreement to be a loop
# (fewer: the joint alignment of neighbouring views already reconciles them).
LOOP_MIN_VIEWS = 2
# The most a chain is taken to drift: a larger disagreement is a wrong alignment.
LOOP_MAX_DEG = 10.0
LOOP_MAX_SHIFT_M = 0.05
# Both alignments must fit as well as the object's alignments usually do, and the old view as well as
# the chain's (photometric RMS): a worse fit is a view that does not show the surface alike (blurred,
# another side), and its disagreement is not the chain's drift.
LOOP_FIT_RATIO = 1.25
# How far the next view's disagreement may differ from the first one's for the loop to be closed.
LOOP_AGREE_DEG = 1.0
LOOP_AGREE_M = 0.005


def closes_loop(references: list[Reference], old: Reference, reached: Reference | None) -> bool:
    """Whether aligning to ``old`` after the chain reached ``reached`` (the view the last pose was
    measured against) closes a loop: the chain from ``old`` to ``reached`` has at least
    ``LOOP_MIN_VIEWS`` links (the views stored between them, and ``reached`` itself, stored or not)."""
    if reached is None or old is reached or old.tau >= reached.tau:
        return False
    return 1 + sum(old.tau < r.tau < reached.tau for r in references) >= LOOP_MIN_VIEWS


def chain_drift(old: Reference, reached: Reference, align: Callable[[Reference], OdometryResult],
                good: Callable[[OdometryResult], bool], typical_rms: float = math.nan) -> torch.Tensor | None:
    """L (4, 4) float64, the object-frame correction that takes the chain's camera-to-object pose of
    the current view (aligned to ``reached``) onto the old view's (aligned to ``old``); None when
    either alignment fails ``good``, fits worse than ``LOOP_FIT_RATIO`` × the usual (``typical_rms``,
    the object's median photometric RMS, and the chain's own fit), or they disagree by more than a chain drifts.

    Args:
        align: the current view aligned to a stored view, alone and without the motion prior
            (:func:`view_aligner`). good: the tracker's test of a usable alignment.
    """
    fits: list[OdometryResult] = []
    for ref in (old, reached):
        fits.append(align(ref))
        if not good(fits[-1]):
            return None
    usual = fits[1].rms_photometric if not math.isfinite(typical_rms) else min(fits[1].rms_photometric, typical_rms)
    if not all(f.rms_photometric <= LOOP_FIT_RATIO * usual for f in fits):  # blurred, or another side
        return None
    C = [ref.C.double() @ res.T_ref_cur.double() for ref, res in zip((old, reached), fits)]
    L = C[0] @ invert_pose(C[1])
    shift, degrees = pose_difference(torch.eye(4, dtype=torch.float64), L)
    return L if degrees <= LOOP_MAX_DEG and shift <= LOOP_MAX_SHIFT_M else None


def view_aligner(pyramid: list[PyramidLevel], T_pred: torch.Tensor, T_wc: torch.Tensor,
                 odometry: OdometryConfig) -> Callable[[Reference], OdometryResult]:
    """The current view (its object pyramid, predicted object-to-world pose T_pred (4, 4), camera-to-world
    T_wc (4, 4)) aligned to a stored view alone, from the prediction, without the motion prior."""
    return lambda ref: track_pyramids(ref.pyramid, pyramid, odometry_init(T_pred, T_wc, ref.C), odometry)


def chain_share(tau: float, start: float, end: float) -> float:
    """How far along the chain from field time ``start`` to ``end`` a view or pose at ``tau`` lies, in [0, 1]."""
    return min(max((tau - start) / max(end - start, 1e-9), 0.0), 1.0)


def spread_drift(L: torch.Tensor, references: list[Reference], track: ObjectTrack, start: float, end: float,
                 until: float = math.inf) -> None:
    """Apply the loop's correction L (4, 4) in place: each stored view (its pose and its object-frame
    points) and each track pose at field time ``start`` < τ < ``until`` by L^w, w = :func:`chain_share`
    (from ``until`` on, the poses were measured against the old view already)."""
    eye = torch.eye(4, dtype=torch.float64)
    share = lambda tau: chain_share(tau, start, end) if tau < until else 0.0  # noqa: E731
    for ref in references:
        w = share(ref.tau)
        if w > 0:
            Lw = interpolate_se3(eye, L, w)
            ref.C = Lw @ ref.C.double()
            if ref.points is not None and len(ref.points):
                ref.points = transform_points(Lw.to(ref.points.dtype), ref.points)
    for tau, pose in zip(track.observed_taus(), track.poses()):
        w = share(tau)
        if w > 0:
            track.add(tau, pose @ invert_pose(interpolate_se3(eye, L, w)))


@dataclass
class LoopCandidate:
    """A loop seen on one view (field time ``tau``): aligned to ``old`` after the chain reached
    ``reached``, the two disagreed by ``L`` (:func:`chain_drift`)."""

    old: Reference
    reached: Reference
    L: torch.Tensor
    tau: float


class ChainLoops:
    """Loop closures of every object's chain, each verified on the object's next view: a loop seen on
    one view (:func:`closes_loop`, :func:`chain_drift`) is closed only if the next view, aligned to the
    same two stored views, disagrees with the chain alike (within ``LOOP_AGREE_DEG`` and
    ``LOOP_AGREE_M``): a lock onto blurred texture is not repeated the same way on the next frame, drift is.
    Counters for metrics.json: loops closed, candidates refused, the largest correction (degrees)."""

    def __init__(self) -> None:
        self.candidates: dict[int, LoopCandidate] = {}
        self.closed, self.refused, self.largest_deg = 0, 0, 0.0

    def step(self, oid: int, references: list[Reference], track: ObjectTrack, picked: Reference, reached: Reference | None,
             tau: float, align: Callable[[Reference], OdometryResult], good: Callable[[OdometryResult], bool],
             typical_rms: float) -> bool:
        """Check object ``oid``'s view at field time ``tau`` (``align``: it aligned to a stored view,
        :func:`view_aligner`), to be aligned to ``picked`` after its last pose was measured against
        ``reached``; True when a loop was closed, and ``references`` and ``track`` corrected (:func:`spread_drift`)."""
        seen = self.candidates.pop(oid, None)
        if seen is not None and track.observed_taus()[-1] == seen.tau:  # the view that saw it was taken: verify
            L = chain_drift(seen.old, seen.reached, align, good, typical_rms)
            shift, degrees = (math.inf, math.inf) if L is None else pose_difference(seen.L, L)
            if L is None or degrees > LOOP_AGREE_DEG or shift > LOOP_AGREE_M:
                self.refused += 1
                return False
            L = interpolate_se3(seen.L, L, 0.5)
            spread_drift(L, references, track, seen.old.tau, seen.reached.tau, until=seen.tau)
            self.closed += 1
            self.largest_deg = max(self.largest_deg, rotation_angle_deg(L))
            return True
        if closes_loop(references, picked, reached):
            L = chain_drift(picked, reached, align, good, typical_rms)
            if L is None:
                self.refused += 1
            else:
                self.candidates[oid] = LoopCandidate(picked, reached, L, tau)
        return False

    def metrics(self) -> dict[str, float | int]:
        return {"object_loops_closed": self.closed, "object_loops_refused": self.refused, "object_loop_largest_deg": self.largest_deg}

    def restore(self, counters: dict[str, float | int]) -> None:
        """The counters of :meth:`metrics` (a resumed run; a loop seen but not yet verified is not kept)."""
        self.closed = int(counters.get("object_loops_closed", 0))
        self.refused = int(counters.get("object_loops_refused", 0))
        self.largest_deg = float(counters.get("object_loop_largest_deg", 0.0))
