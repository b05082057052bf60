"""An object's keyframe observations (references) and which of them a new view is aligned to."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from tivne.slam.tracking.pyramid import PyramidLevel

# A stored view is reused when it saw the object from within this angle of the predicted view, and
# from a distance within this factor of the predicted one.
REUSE_ANGLE_DEG = 12.0
DISTANCE_RATIO = 1.25


@dataclass
class Reference:
    """An object's keyframe observation: its pyramid (object pixels only), camera-to-object pose,
    field time, number of object pixels and its (M, 3) object-frame points (a subsample)."""

    pyramid: list[PyramidLevel]
    C: torch.Tensor
    tau: float
    pixels: int = 0
    points: torch.Tensor | None = None


def view_direction(C: torch.Tensor) -> torch.Tensor:
    """(3,) unit direction from the object origin to the camera of camera-to-object pose C (4, 4)."""
    return C[:3, 3] / C[:3, 3].norm().clamp_min(1e-9)


def _seen_alike(references: list[Reference], C_pred: torch.Tensor, max_angle_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) cosines between each stored view's direction and that of the predicted view C_pred (4, 4),
    and (N,) bool: the view was taken from within ``max_angle_deg`` of C_pred's direction and from a
    distance within ``DISTANCE_RATIO`` of C_pred's."""
    d_pred, dist_pred = view_direction(C_pred), float(C_pred[:3, 3].norm())
    cosines = torch.stack([view_direction(ref.C) @ d_pred for ref in references])
    ratio = torch.stack([ref.C[:3, 3].norm() for ref in references]) / max(dist_pred, 1e-9)
    same_distance = (ratio >= 1.0 / DISTANCE_RATIO) & (ratio <= DISTANCE_RATIO)
    return cosines, (cosines >= float(np.cos(np.radians(max_angle_deg)))) & same_distance


def pick_reference(references: list[Reference], C_pred: torch.Tensor, max_angle_deg: float) -> Reference:
    """The oldest keyframe that saw the object from within ``max_angle_deg`` of the predicted view
    and from a distance within 25 %, else the one whose view is nearest in direction (the newest of
    equals): tracking against the oldest usable view, not a chain of the latest ones, keeps the
    object's drift from growing with every new keyframe; and a turning object seen again from a
    side an older keyframe saw is aligned to that one, not to the newest, which saw another side."""
    cosines, usable = _seen_alike(references, C_pred, max_angle_deg)
    usable[-1] = False  # the newest is the fallback's, by direction alone
    if bool(usable.any()):
        return references[int(usable.nonzero()[0, 0])]
    return references[max(range(len(references)), key=lambda i: (float(cosines[i]), i))]


def comparable_view(references: list[Reference], C_pred: torch.Tensor, pixels: int, max_angle_deg: float) -> Reference:
    """The stored view to centre an object seen again on (:func:`centred_on`) and to align it to: of
    those that saw it from within ``max_angle_deg`` of the predicted view C_pred (4, 4) and from a
    distance within 25 %, the one that showed about as much of it as the ``pixels`` seen now (scaled
    to the distance), else :func:`pick_reference`'s. Where a side's centre lies depends on how much
    of the side is seen, so a view cut by an occluder centres a whole one off by up to half the
    object, and a whole view overlaps it too little to be aligned to it."""
    near = _seen_alike(references, C_pred, max_angle_deg)[1].nonzero().flatten().tolist()
    if not near:
        return pick_reference(references, C_pred, max_angle_deg)
    dist = float(C_pred[:3, 3].norm())

    def mismatch(ref: Reference) -> float:  # |log| of the ratio of what the view showed to what is seen now
        return abs(math.log(max(ref.pixels * (float(ref.C[:3, 3].norm()) / max(dist, 1e-9)) ** 2, 1.0) / max(pixels, 1)))

    return min((references[i] for i in near), key=mismatch)


def companions(references: list[Reference], ref: Reference, C_pred: torch.Tensor, max_angle_deg: float, count: int) -> list[Reference]:
    """Up to ``count`` stored views besides ``ref`` that also saw the object from within
    ``max_angle_deg`` of the predicted view C_pred (4, 4) and from a distance within 25 %, nearest
    in direction first: aligned jointly with ``ref``, their pixels average out each single view's
    noise and pose error (a symmetric object's spin rests on its texture, seen a little differently
    in each view)."""
    cosines, near = _seen_alike(references, C_pred, max_angle_deg)
    order = sorted((i for i in range(len(references)) if bool(near[i]) and references[i] is not ref), key=lambda i: (-float(cosines[i]), i))
    return [references[i] for i in order[:count]]


def add_reference(references: list[Reference], new: Reference, limit: int) -> list[Reference]:
    """``references`` (oldest first) with ``new`` appended, at most ``limit`` kept: beyond it, of the
    two views nearest in direction the newer goes (``new`` too, when an older view saw its side), so
    the stored views keep covering every side seen, the oldest always among them: a turning object
    is aligned to its first views again after a whole turn, which ends the drift of the chain in
    between (keeping the newest only, a turn outlives its first views), and of two views of one side
    the older, less drifted one stays. Views from distances more than 25 % apart count as far apart."""
    refs = [*references, new]
    while len(refs) > max(limit, 1):
        dirs = torch.stack([view_direction(r.C) for r in refs])
        dist = torch.stack([r.C[:3, 3].norm() for r in refs])
        ratio = dist[:, None] / dist[None, :].clamp_min(1e-9)
        far = (ratio < 1.0 / DISTANCE_RATIO) | (ratio > DISTANCE_RATIO)  # not the same view, whatever the direction
        similar = (dirs @ dirs.T) - 4.0 * far.to(dirs.dtype)
        older = torch.ones_like(far).tril(-1)  # row j: the views older than j
        refs.pop(1 + int(similar.masked_fill(~older, -math.inf)[1:].max(1).values.argmax()))
    return refs


def shows_enough(pixels: int, distance: float, ref: Reference, share: float = 0.5) -> bool:
    """Whether a view of ``pixels`` object pixels from ``distance`` (m) shows at least ``share`` of
    what ``ref`` showed, scaled to that distance (an object twice as far covers a quarter of the
    pixels): less means it is cut by the border or occluded."""
    ratio = float(ref.C[:3, 3].norm()) / max(distance, 1e-9)
    return pixels >= share * ref.pixels * ratio**2


def centred_on(T_wo: torch.Tensor, ref: Reference, centre: torch.Tensor, R_wc: torch.Tensor, middle: torch.Tensor | None = None) -> torch.Tensor:
    """(4, 4) ``T_wo`` moved so that the object's ``middle`` (3,) (object frame, e.g. the centre of
    its observed extent; None: its origin) sits, relative to ``centre`` (3,) (the centre of the
    object points seen now, world) and in the current camera's axes ``R_wc`` (3, 3), where it sat
    relative to the centre of what ``ref`` saw, in that camera's axes: the centre of a visible side
    lies between the camera and the object's middle, and where is a matter of the view, not of the
    object's unknown rotation; the origin then follows the pose's rotation (kept as it is). So a
    sliver's centre or another side's does not shift the object. Unchanged when ``ref`` holds no points."""
    if ref.points is None or not len(ref.points):
        return T_wo
    T = T_wo.clone()
    m = torch.zeros(3, dtype=T.dtype) if middle is None else middle.to(T)
    middle_in_ref_camera = ref.C[:3, :3].T.to(T) @ (m - ref.points.mean(0).to(T))  # middle − seen centre, ref camera axes
    T[:3, 3] = centre.to(T) + R_wc.to(T) @ middle_in_ref_camera - T[:3, :3] @ m
    return T
