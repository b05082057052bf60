"""Seeds -> whole objects: depth-continuous segments of a frame and the mask clean-up (numpy)."""

from __future__ import annotations

import numpy as np
import torch

from tivne.morphology import dilate, erode


def concave_creases(depth: np.ndarray, sigmas: float, span: int = 2) -> np.ndarray:
    """(H, W) bool: pixels on a concave crease, where two surfaces meet in a valley seen from the
    camera (an object standing on the floor, a door at the floor or wall, a box against a wall).

    On a plane, inverse depth q = 1/z is affine in the pixel coordinates for any pinhole camera, so
    its second difference over ``span`` pixels, q(x - span) + q(x + span) - 2 q(x), is 0 whatever
    the plane's slant; at a concave crease the middle lies behind its neighbours' chord and the
    difference is positive, at a convex edge (a box's corner, a ball's limb) negative. A pixel is on
    a crease when the difference along a row or a column exceeds ``sigmas`` times its noise,
    √6 σ_q with σ_q = σ(z) / z² (σ(z): :func:`data_modules.sensor.kinect_depth_sigma`).

    Args:
        depth: (H, W) metres, 0 = invalid. sigmas: threshold in noise units. span: pixels to each side.
    """
    from data_modules.sensor import kinect_depth_sigma

    d = depth.astype(np.float64)
    valid = d > 0
    safe = np.where(valid, d, 1.0)
    q = np.where(valid, 1.0 / safe, 0.0)
    limit = sigmas * np.sqrt(6.0) * kinect_depth_sigma(safe) / safe**2
    crease = np.zeros_like(valid)
    # Along the columns, then along the rows: the transposes are views, so crease.T is written through.
    for qq, vv, ll, out in ((q, valid, limit, crease), (q.T, valid.T, limit.T, crease.T)):
        if qq.shape[0] > 2 * span:
            second = qq[: -2 * span] + qq[2 * span :] - 2.0 * qq[span:-span]
            both = vv[: -2 * span] & vv[2 * span :] & vv[span:-span]
            out[span:-span] |= both & (second > ll[span:-span])
    return crease


def depth_segments(
    depth: np.ndarray, rel_jump: float = 0.1, abs_jump: float = 0.03, crease_sigmas: float | None = None, crease_span: int = 2,
    hole_edges: bool = True,
) -> tuple[np.ndarray, int]:
    """Label depth-continuous regions: neighbours join when |Δz| <= max(abs_jump, rel_jump · z);
    with ``crease_sigmas``, concave creases (:func:`concave_creases`) also separate them: an object
    resting on the floor or a door near it is depth-continuous with the room at the contact and
    would otherwise be one segment with the whole background. With ``hole_edges`` a valid pixel
    beside an invalid one (a sensor shadow, common along silhouettes) is an edge too: at full
    resolution that costs an object one pixel of rim (the objects' own pixels keep that rule,
    :func:`tivne.slam.objects.instances.mask_segments`); at a motion mask's low resolution the same
    rim is most of a small object (:func:`clean_mask` turns it off).

    Args:
        depth: (H, W) metres, 0 = invalid (never labelled).
    Returns:
        labels (H, W) int32 (0 = invalid, depth edge or crease), number of labels.
    """
    from scipy import ndimage

    d = depth.astype(np.float32)
    valid = d > 0
    thr = np.maximum(abs_jump, rel_jump * d)
    edge = np.zeros_like(valid)
    dx = np.abs(d[:, 1:] - d[:, :-1]) > np.minimum(thr[:, 1:], thr[:, :-1])
    dy = np.abs(d[1:, :] - d[:-1, :]) > np.minimum(thr[1:, :], thr[:-1, :])
    if not hole_edges:  # only a jump between two valid depths parts them; a hole belongs to no segment anyway
        dx &= valid[:, 1:] & valid[:, :-1]
        dy &= valid[1:, :] & valid[:-1, :]
    # The far side of a jump is the edge: the near (occluding) side keeps its silhouette.
    far_x = d[:, 1:] > d[:, :-1]
    edge[:, 1:] |= dx & far_x
    edge[:, :-1] |= dx & ~far_x
    far_y = d[1:, :] > d[:-1, :]
    edge[1:, :] |= dy & far_y
    edge[:-1, :] |= dy & ~far_y
    inner = valid & ~edge
    if crease_sigmas is not None:
        inner &= ~concave_creases(depth, crease_sigmas, crease_span)
    labels, n = ndimage.label(inner)
    return labels.astype(np.int32), int(n)


def clean_mask(
    seeds: np.ndarray,
    depth: np.ndarray,
    previous: np.ndarray | None = None,
    open_radius: int = 1,
    min_area: int = 20,
    seed_fraction: float = 0.08,
    keep_fraction: float = 0.5,
    max_area_fraction: float = 0.4,
    rel_jump: float = 0.1,
    abs_jump: float = 0.03,
    close_radius: int = 1,
    motion_score: np.ndarray | None = None,
    score_threshold: float = 3.0,
    score_ratio: float = 2.0,
    crease_sigmas: float | None = None,
    crease_span: int = 2,
) -> np.ndarray:
    """Residual seeds -> a clean object mask (pure function, numpy).

    1. Opening removes speckle and one-pixel slivers from the seeds.
    2. The frame is split into depth-continuous segments (:func:`depth_segments`, holes not cutting); a segment is
       dynamic when its seeds cover >= ``seed_fraction`` of it, or (temporal consistency) when
       >= ``keep_fraction`` of it was dynamic in ``previous``; segments smaller than ``min_area`` px
       or larger than ``max_area_fraction`` of the valid pixels (the static background) never are.
       With ``motion_score`` (per-pixel |residual| / σ(z) against an earlier frame, NaN where
       unknown) a segment is also dynamic when its median score reaches ``score_threshold`` and
       ``score_ratio`` times the largest segment's (the background's, so a pose error that moves
       everything does not fire): averaging over the segment catches motion far below the per-pixel
       seed threshold. With ``crease_sigmas`` segments also end at concave creases
       (:func:`concave_creases`): an object on the floor, or a door, is depth-continuous with the
       room and would otherwise be part of the background.
    3. Closing fills holes; the result is restricted to valid depth.

    Args:
        seeds: (H, W) bool. depth: (H, W) metres. previous: (H, W) bool or None.
    Returns:
        (H, W) bool.
    """
    from scipy import ndimage

    valid = depth > 0
    s = seeds & valid
    if open_radius > 0:
        s = opening(s, open_radius)
    # Holes do not cut: at the mask's stride a ball of 22 pixels kept 9 beside its shadow, fell under
    # min_area and went unmasked for seconds (three_objects' circler, 4.1 cm at 90 %).
    labels, n = depth_segments(depth, rel_jump, abs_jump, crease_sigmas, crease_span, hole_edges=False)
    if n == 0:
        return np.zeros_like(valid)
    idx = np.arange(1, n + 1)
    area = ndimage.sum_labels(np.ones_like(labels), labels, idx)
    seed_px = ndimage.sum_labels(s, labels, idx)
    keep = seed_px >= seed_fraction * area
    if motion_score is not None:
        scored = np.where(np.isfinite(motion_score), labels, 0)
        n_scored = ndimage.sum_labels(np.ones_like(scored), scored, idx)
        med = np.asarray(ndimage.median(np.nan_to_num(np.abs(motion_score)), scored, idx), dtype=np.float64)
        med = np.where(n_scored >= min_area, med, 0.0)
        background = med[int(np.argmax(area))]
        keep |= (med >= score_threshold) & (med >= score_ratio * background) & (n_scored >= 0.5 * area)
    if previous is not None and previous.shape == labels.shape and previous.any():
        keep |= ndimage.sum_labels(previous, labels, idx) >= keep_fraction * area
    keep &= (area >= min_area) & (area <= max_area_fraction * max(int(valid.sum()), 1))
    lut = np.zeros(n + 1, bool)
    lut[1:] = keep
    out = lut[labels]
    if out.any():
        # Give the segments back their edge pixels that sit at the segment's depth.
        ring = ndimage.binary_dilation(out) & ~out & valid
        dsum = ndimage.uniform_filter(np.where(out, depth, 0.0).astype(np.float64), 3)
        csum = ndimage.uniform_filter(out.astype(np.float64), 3)
        nbr = dsum / np.maximum(csum, 1e-9)
        out |= ring & (np.abs(depth - nbr) <= np.maximum(abs_jump, rel_jump * depth))
        if close_radius > 0:
            out = closing(out, close_radius)
    return out & valid


def opening(mask: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool opening with a square window, nothing beyond the image (:mod:`tivne.morphology`)."""
    m = torch.from_numpy(np.ascontiguousarray(mask))
    return dilate(erode(m, radius), radius).numpy()


def closing(mask: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool closing with a square window, nothing beyond the image: a segment the image border
    cuts keeps its border pixels. (scipy's closing with a 0 border took them, so a geometric mask
    stopped a stride short of the edge and the object tracker never saw an object there as cut off.)"""
    m = torch.from_numpy(np.ascontiguousarray(mask))
    return erode(dilate(m, radius), radius).numpy()
