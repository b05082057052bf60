"""Model-free (geometric) motion masks: pixels observed in space that was seen as free before."""

from __future__ import annotations

import time

import numpy as np
import torch

from data_modules.frame import Frame
from data_modules.sensor import kinect_depth_sigma
from tivne.masks.base import MaskContext, MaskProvider
from tivne.render.rays import rays_from_pixels


def residual_seeds(
    observed: torch.Tensor,
    rendered: torch.Tensor,
    known: torch.Tensor,
    abs_threshold: float = 0.08,
    k_sigma: float = 6.0,
    color_residual: torch.Tensor | None = None,
    color_threshold: float | None = None,
) -> torch.Tensor:
    """Pixels where the observation is *in front of* the map: something now occupies space the map
    saw as free. That sign marks the moving object's current pixels; the opposite sign (observed
    behind the map) is disoccluded background where the object was and is left out.

    Args:
        observed, rendered: (H, W) depth in metres (0 = invalid observation).
        known: (H, W) bool, the map has a surface along the ray (not newly observed space).
        color_residual: optional (H, W) colour L1 (mean over channels); flags pixels whose depth
            agrees with the map (|r| < threshold) but whose colour does not.
    Returns:
        (H, W) bool.
    """
    thr = torch.clamp(k_sigma * kinect_depth_sigma(observed), min=abs_threshold)
    valid = known & (observed > 0)
    seeds = valid & (rendered - observed > thr)
    if color_residual is not None and color_threshold is not None and color_threshold > 0:
        seeds = seeds | (valid & ((observed - rendered).abs() <= thr) & (color_residual > color_threshold))
    return seeds


def depth_segments(depth: np.ndarray, rel_jump: float = 0.1, abs_jump: float = 0.03) -> tuple[np.ndarray, int]:
    """Label depth-continuous regions: neighbours join when |Δz| <= max(abs_jump, rel_jump · z).

    Args:
        depth: (H, W) metres, 0 = invalid (never labelled).
    Returns:
        labels (H, W) int32 (0 = invalid or depth edge), number of labels.
    """
    from scipy import ndimage

    d = depth.astype(np.float32)
    valid = d > 0
    thr = np.maximum(abs_jump, rel_jump * d)
    edge = np.zeros_like(valid)
    dx = np.abs(d[:, 1:] - d[:, :-1]) > np.minimum(thr[:, 1:], thr[:, :-1])
    dy = np.abs(d[1:, :] - d[:-1, :]) > np.minimum(thr[1:, :], thr[:-1, :])
    # The far side of a jump is the edge: the near (occluding) side keeps its silhouette.
    far_x = d[:, 1:] > d[:, :-1]
    edge[:, 1:] |= dx & far_x
    edge[:, :-1] |= dx & ~far_x
    far_y = d[1:, :] > d[:-1, :]
    edge[1:, :] |= dy & far_y
    edge[:-1, :] |= dy & ~far_y
    inner = valid & ~edge
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
) -> np.ndarray:
    """Residual seeds -> a clean object mask (pure function, numpy).

    1. Opening removes speckle and one-pixel slivers from the seeds.
    2. The frame is split into depth-continuous segments (:func:`depth_segments`); a segment is
       dynamic when its seeds cover >= ``seed_fraction`` of it, or (temporal consistency) when
       >= ``keep_fraction`` of it was dynamic in ``previous``; segments smaller than ``min_area`` px
       or larger than ``max_area_fraction`` of the valid pixels (the static background) never are.
       With ``motion_score`` (per-pixel |residual| / σ(z) against an earlier frame, NaN where
       unknown) a segment is also dynamic when its median score reaches ``score_threshold`` and
       ``score_ratio`` times the largest segment's (the background's, so a pose error that moves
       everything does not fire): averaging over the segment catches motion far below the per-pixel
       seed threshold.
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
        s = ndimage.binary_opening(s, structure=np.ones((2 * open_radius + 1,) * 2, bool))
    labels, n = depth_segments(depth, rel_jump, abs_jump)
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
            out = ndimage.binary_closing(out, structure=np.ones((2 * close_radius + 1,) * 2, bool), border_value=0)
    return out & valid


@torch.no_grad()
def march_map_depth(
    field: torch.nn.Module,
    pose: torch.Tensor,
    K: torch.Tensor,
    uv: torch.Tensor,
    tau: float,
    near: float,
    far: float,
    step: float,
    chunk: int = 4096,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where the map's first surface lies along pixel rays (sphere-free SDF marching).

    Samples every ``step`` metres in [near, far], finds the first + to - sign change of the SDF among
    allocated samples (unallocated space counts as free) and interpolates linearly.

    Args:
        uv: (N, 2) pixel coordinates. pose: (4, 4) c2w.
    Returns:
        depth (N,) z-depth of the surface (0 where none), known (N,) bool, rgb (N, 3) at the surface.
    """
    n_s = max(int(np.ceil((far - near) / step)) + 1, 2)
    z = torch.linspace(near, far, n_s, device=uv.device, dtype=K.dtype)
    out_d, out_k, out_c = [], [], []
    per = max(chunk // n_s, 64)  # rays per forward pass
    for start in range(0, uv.shape[0], per):
        o, d = rays_from_pixels(uv[start : start + per].to(K.dtype), K, pose)
        pts = o[:, None, :] + d[:, None, :] * z[None, :, None]
        m = pts.shape[0]
        f = field(pts.reshape(-1, 3), torch.full((m * n_s,), float(tau), device=uv.device, dtype=K.dtype))
        sdf = torch.where(f.valid, f.sdf, torch.ones_like(f.sdf)).view(m, n_s)
        crossing = (sdf[:, :-1] > 0) & (sdf[:, 1:] <= 0) & f.valid.view(m, n_s)[:, 1:]
        has = crossing.any(dim=1)
        i = crossing.float().argmax(dim=1)
        s0 = sdf.gather(1, i[:, None])[:, 0]
        s1 = sdf.gather(1, (i + 1)[:, None])[:, 0]
        frac = (s0 / (s0 - s1).clamp_min(1e-6)).clamp(0, 1)
        depth = torch.where(has, z[i] + frac * (z[1] - z[0]), torch.zeros_like(s0))
        rgb = f.rgb.view(m, n_s, 3)
        c = rgb.gather(1, (i + 1)[:, None, None].expand(-1, 1, 3))[:, 0]
        out_d.append(depth)
        out_k.append(has)
        out_c.append(c)
    return torch.cat(out_d), torch.cat(out_k), torch.cat(out_c)


def upsample_mask(low: torch.Tensor, stride: int, like: torch.Tensor) -> torch.Tensor:
    """(h, w) bool mask of every ``stride``-th pixel -> (H, W) bool like ``like`` (nearest; the
    border beyond a multiple of the stride stays False)."""
    h, w = like.shape[-2:]
    full = low.to(like.device).repeat_interleave(stride, 0).repeat_interleave(stride, 1)[:h, :w]
    if full.shape != (h, w):
        pad = torch.zeros(h, w, dtype=torch.bool, device=like.device)
        pad[: full.shape[0], : full.shape[1]] = full
        full = pad
    return full


@torch.no_grad()
def free_space_seeds(
    depth: torch.Tensor,
    pose: torch.Tensor,
    ref_depth: torch.Tensor,
    ref_pose: torch.Tensor,
    K: torch.Tensor,
    abs_threshold: float = 0.08,
    k_sigma: float = 6.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels whose observed point lies in space an earlier frame saw as free (static-world test).

    Each valid pixel is back-projected with ``depth`` and ``pose``, moved into the reference camera
    and compared with the reference depth there (the minimum over a 3x3 neighbourhood, so static
    silhouettes do not fire): ``z_ref(X) < d_ref - thr`` means the point was empty space then, so
    something moved *into* it -- the moving object's current pixels. Disoccluded background
    (``z_ref(X) > d_ref``) is not flagged.

    Args:
        depth, ref_depth: (H, W) metres, 0 = invalid. pose, ref_pose: (4, 4) c2w. K: (3, 3) for (H, W).
    Returns:
        seeds (H, W) bool, known (H, W) bool (the reference saw the point's pixel), and residual
        (H, W) float: (z_ref(X) - d_ref) / σ(d_ref) at the nearest reference pixel (no 3x3 minimum;
        NaN where not known), the signed static-world residual in noise units.
    """
    h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, device=depth.device), torch.arange(w, device=depth.device), indexing="ij")
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    cam = torch.stack([x, y, depth], dim=-1).reshape(-1, 3)
    rel = torch.linalg.solve(ref_pose.to(cam.dtype), pose.to(cam.dtype))  # current camera -> reference camera
    p = cam @ rel[:3, :3].T + rel[:3, 3]
    z = p[:, 2]
    ur = torch.round(p[:, 0] / z.clamp_min(1e-6) * K[0, 0] + K[0, 2]).long()
    vr = torch.round(p[:, 1] / z.clamp_min(1e-6) * K[1, 1] + K[1, 2]).long()
    inb = (z > 1e-3) & (ur >= 0) & (ur < w) & (vr >= 0) & (vr < h)
    inf = torch.where(ref_depth > 0, ref_depth, torch.full_like(ref_depth, float("inf")))
    dmin = -torch.nn.functional.max_pool2d(-inf[None, None], 3, stride=1, padding=1)[0, 0]
    d_ref = torch.zeros_like(z)
    d_ref[inb] = dmin[vr[inb], ur[inb]]
    known = inb & torch.isfinite(d_ref) & (depth.reshape(-1) > 0)
    thr = torch.clamp(k_sigma * kinect_depth_sigma(d_ref.clamp(max=20.0)), min=abs_threshold)
    seeds = known & (z < d_ref - thr)
    d_centre = torch.zeros_like(z)
    d_centre[inb] = ref_depth[vr[inb], ur[inb]]
    scored = known & (d_centre > 0)
    residual = torch.full_like(z, float("nan"))
    residual[scored] = (z[scored] - d_centre[scored]) / kinect_depth_sigma(d_centre[scored])
    return seeds.view(h, w), known.view(h, w), residual.view(h, w)


class GeometricMasks(MaskProvider):
    """Model-free motion masks (``needs_tracked_pose``): pixels observed in space seen as free before.

    ``source='frames'`` (default): the frame's points, placed with the tracked pose, are tested
    against earlier frames ``lags`` back (their depth and tracked pose; :func:`free_space_seeds`).
    ``source='map'``: the map is ray-marched at the tracked pose at a reference time (``reference``:
    'last_mapped' = the latest time the map was trained on; 'frame' = the frame's own τ; 'first' =
    τ = 0) and pixels observed in front of its surface where it knows one are seeds
    (:func:`residual_seeds`). On the moving cube the time-varying map follows the object (it is
    trained on it every frame), so map residuals stay at the noise level and 'map' finds nothing
    there; earlier *frames* do not adapt, hence the default.

    Both test every ``stride``-th pixel with threshold max(abs_threshold, k_sigma·σ(z)), and only the
    sign "observed in front of what was seen" (the object's current pixels, not the background it
    uncovered). :func:`clean_mask` turns seeds into whole objects (opening, depth-continuous
    segments, area limits, the previous frame's mask for temporal consistency, closing); the mask is
    upsampled (nearest) to the frame size. ``predict`` gives tracking the previous mask, grown.
    The first frame gets an all-static mask. With ``source='frames'`` a segment is also dynamic when
    its median |static-world residual| / σ(z) reaches ``score_threshold`` (and ``score_ratio`` times
    the background's), which catches slow motion within a few frames, and ``revise`` re-tests
    keyframes ``revise_lags`` frames back against each new frame.
    """

    name = "geometric"
    needs_tracked_pose = True

    def __init__(
        self,
        source: str = "frames",
        lags: tuple[int, ...] = (5, 30),
        reference: str = "last_mapped",
        stride: int = 4,
        abs_threshold: float = 0.03,
        k_sigma: float = 6.0,
        color_threshold: float | None = None,
        far: float = 8.0,
        step: float = 0.04,
        open_radius: int = 1,
        close_radius: int = 1,
        min_area: int = 12,
        seed_fraction: float = 0.04,
        keep_fraction: float = 0.5,
        max_area_fraction: float = 0.4,
        rel_jump: float = 0.1,
        abs_jump: float = 0.03,
        temporal: bool = True,
        predict_margin: int = 2,
        revise_lags: tuple[int, int] | None = (5, 30),
        score_threshold: float | None = 3.0,
        score_ratio: float = 2.0,
    ) -> None:
        if source not in ("frames", "map"):
            raise ValueError(f"masks.source must be 'frames' or 'map', got {source!r}")
        if reference not in ("last_mapped", "frame", "first"):
            raise ValueError(f"masks.reference must be 'last_mapped', 'frame' or 'first', got {reference!r}")
        if stride < 1:
            raise ValueError(f"masks.stride must be >= 1, got {stride}")
        self.source = source
        self.lags = tuple(int(x) for x in lags)
        self.history: list[tuple[int, torch.Tensor, torch.Tensor]] = []  # (frame_number, low-res depth, pose)
        self.reference = reference
        self.stride = int(stride)
        self.abs_threshold = abs_threshold
        self.k_sigma = k_sigma
        self.color_threshold = color_threshold
        self.far = far
        self.step = step
        self.clean_kwargs = dict(
            open_radius=open_radius, close_radius=close_radius, min_area=min_area, seed_fraction=seed_fraction,
            keep_fraction=keep_fraction, max_area_fraction=max_area_fraction, rel_jump=rel_jump, abs_jump=abs_jump,
        )
        self.temporal = temporal
        self.revise_lags = None if revise_lags is None else (int(revise_lags[0]), int(revise_lags[1]))
        self.use_score = score_threshold is not None
        if self.use_score:
            self.clean_kwargs |= dict(score_threshold=float(score_threshold), score_ratio=float(score_ratio))
        self.predict_margin = int(predict_margin)
        self.previous: np.ndarray | None = None  # low-resolution mask of the previous frame
        self._previous_tau: float | None = None
        self.timings_ms: list[float] = []
        self.last_debug: dict[str, np.ndarray] = {}

    def reference_tau(self, context: MaskContext) -> float:
        if self.reference == "frame":
            return float(context.tau)
        if self.reference == "first":
            return 0.0
        if context.last_mapped_tau is not None:
            return float(context.last_mapped_tau)
        # The caller does not pass it: with mapping every frame it is the previous frame's time.
        return float(self._previous_tau if self._previous_tau is not None else context.tau)

    def __call__(self, frame: Frame, context: MaskContext | None) -> torch.Tensor | None:
        start = time.perf_counter()
        h, w = frame.height, frame.width
        s = self.stride
        depth = frame.depth[::s, ::s]
        if context is None or context.frame_number == 0:
            self._previous_tau = None if context is None else float(context.tau)
            self.previous = None
            self.history = [] if context is None else [(0, depth.clone(), context.pose.detach().clone())]
            return torch.zeros(h, w, dtype=torch.bool, device=frame.depth.device)
        score = None
        if self.source == "frames":
            seeds, score = self._frame_seeds(depth, context)
            rd = known = None
        else:
            seeds, rd, known = self._map_seeds(frame, depth, context)
        dnp = depth.cpu().numpy()
        previous = self.previous if self.temporal else None
        low = clean_mask(seeds.cpu().numpy(), dnp, previous, motion_score=self._score(score), **self.clean_kwargs)
        self.previous = low
        self._previous_tau = float(context.tau)
        self.last_debug = {"seeds": seeds.cpu().numpy()}
        if rd is not None:
            self.last_debug |= {"rendered": rd.cpu().numpy(), "known": known.cpu().numpy()}
        full = upsample_mask(torch.from_numpy(low), s, frame.depth) & (frame.depth > 0)
        self.timings_ms.append(1000 * (time.perf_counter() - start))
        return full

    def predict(self, frame: Frame) -> torch.Tensor | None:
        """The previous frame's mask dilated by ``predict_margin`` low-resolution pixels (objects move
        little between frames), at the frame size: what tracking should leave out before this frame's
        own mask exists. None before the first mask."""
        if self.previous is None:
            return None
        low = torch.from_numpy(self.previous)[None, None].float()
        r = self.predict_margin
        if r > 0:
            low = torch.nn.functional.max_pool2d(low, 2 * r + 1, stride=1, padding=r)
        return upsample_mask(low[0, 0] > 0, self.stride, frame.depth)

    def revise(self, keyframes: list, current, K: torch.Tensor) -> int:
        """The static-world test backwards: a keyframe's points that the current frame sees as free
        space have moved away since. With ``revise_lags`` = (a, b), keyframes a..b frames back are
        re-tested against the current frame and their masks grow by the cleaned result (never
        shrink), so the object is masked in them -- and in mapping -- even where it was still too
        slow to be caught when they were taken (``source='frames'`` only)."""
        if self.source != "frames" or self.revise_lags is None:
            return 0
        s = self.stride
        lo, hi = self.revise_lags
        ref_depth = current.depth[::s, ::s]
        Kl = self._low_K(K)
        grown = 0
        for kf in keyframes:
            if not lo <= current.frame_id - kf.frame_id <= hi:
                continue
            depth = kf.depth[::s, ::s]
            seeds, _, residual = free_space_seeds(depth, kf.pose, ref_depth, current.pose, Kl, self.abs_threshold, self.k_sigma)
            old = None if kf.dynamic is None else kf.dynamic[::s, ::s].cpu().numpy()
            low = clean_mask(seeds.cpu().numpy(), depth.cpu().numpy(), old, motion_score=self._score(residual), **self.clean_kwargs)
            full = upsample_mask(torch.from_numpy(low), s, kf.depth) & (kf.depth > 0)
            new = full if kf.dynamic is None else full | kf.dynamic
            if kf.dynamic is None or bool((new & ~kf.dynamic).any()):
                kf.dynamic = new
                grown += 1
        return grown

    def _score(self, residual: torch.Tensor | None) -> np.ndarray | None:
        """The segment-level motion score for :func:`clean_mask` (None when that test is off)."""
        return None if residual is None or not self.use_score else residual.cpu().numpy()

    def _low_K(self, K: torch.Tensor) -> torch.Tensor:
        Kl = K.clone()
        Kl[:2] /= self.stride  # pixel (i*s) of the frame is pixel i here
        return Kl

    def _frame_seeds(self, depth: torch.Tensor, context: MaskContext) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Free-space seeds against every lag's reference frame, and the normalised residual against
        the first one (the segment motion score)."""
        k = int(context.frame_number)
        score = None
        pose = context.pose.detach().clone()
        Kl = self._low_K(context.K)
        seeds = torch.zeros_like(depth, dtype=torch.bool)
        used = set()
        for lag in self.lags:
            # the stored frame closest to `lag` frames back (the oldest one early in the sequence)
            ref = min(self.history, key=lambda e: abs((k - e[0]) - lag))
            if ref[0] in used:
                continue
            used.add(ref[0])
            s, _, residual = free_space_seeds(depth, pose, ref[1], ref[2], Kl, self.abs_threshold, self.k_sigma)
            seeds |= s
            score = residual if score is None else score
        self.history.append((k, depth.clone(), pose))
        horizon = max(self.lags) + 1
        self.history = [e for e in self.history if k - e[0] <= horizon]
        return seeds, score

    def _map_seeds(self, frame: Frame, depth: torch.Tensor, context: MaskContext):
        s = self.stride
        device = depth.device
        hs, ws = depth.shape
        v, u = torch.meshgrid(torch.arange(hs, device=device) * s, torch.arange(ws, device=device) * s, indexing="ij")
        uv = torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1).float()
        r = context.render
        near = float(getattr(r, "near", 0.05))
        far = max(self.far, float(depth.max()) + 0.5)
        tau_ref = self.reference_tau(context)
        rd, known, rc = march_map_depth(context.field, context.pose, context.K, uv, tau_ref, near, far, self.step)
        rd, known = rd.view(hs, ws), known.view(hs, ws)
        color_res = None
        if self.color_threshold:
            color_res = (rc.view(hs, ws, 3) - frame.rgb[::s, ::s]).abs().mean(-1)
        seeds = residual_seeds(depth, rd, known, self.abs_threshold, self.k_sigma, color_res, self.color_threshold)
        return seeds, rd, known


