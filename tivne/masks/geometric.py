"""Model-free (geometric) motion masks: pixels observed in space that was seen as free before.

The provider holds the state (earlier frames, the previous mask); the static-world checks are pure
functions in :mod:`tivne.masks.seeds` (seeds against earlier frames or the map) and
:mod:`tivne.masks.segments` (seeds -> depth-continuous objects). σ(z) is the sensor's depth noise,
:func:`data_modules.sensor.kinect_depth_sigma`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from data_modules.frame import Frame
from tivne.geometry import pixel_grid
from tivne.masks.base import MaskContext, MaskProvider
from tivne.masks.seeds import free_space_seeds, march_map_depth, residual_seeds
from tivne.masks.segments import clean_mask
from tivne.masks.settings import GeometricMasksConfig
from tivne.morphology import dilate


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

    def __init__(self, **settings: Any) -> None:
        """``settings``: :class:`tivne.masks.settings.GeometricMasksConfig` keys (checked there, with
        their defaults; a bad value is one line naming ``masks.provider.<key>``)."""
        cfg = GeometricMasksConfig(**settings)
        source, lags, reference, stride = cfg.source, cfg.lags, cfg.reference, cfg.stride
        abs_threshold, k_sigma, color_threshold, far, step = cfg.abs_threshold, cfg.k_sigma, cfg.color_threshold, cfg.far, cfg.step
        open_radius, close_radius, min_area, seed_fraction = cfg.open_radius, cfg.close_radius, cfg.min_area, cfg.seed_fraction
        keep_fraction, max_area_fraction, rel_jump, abs_jump = cfg.keep_fraction, cfg.max_area_fraction, cfg.rel_jump, cfg.abs_jump
        temporal, predict_margin, revise_lags = cfg.temporal, cfg.predict_margin, cfg.revise_lags
        score_threshold, score_ratio = cfg.score_threshold, cfg.score_ratio
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
            crease_sigmas=cfg.crease_sigmas, crease_span=cfg.crease_span,
        )
        self.temporal = temporal
        self.revise_lags = None if revise_lags is None else (int(revise_lags[0]), int(revise_lags[1]))
        self.use_score = score_threshold is not None
        if self.use_score:
            self.clean_kwargs |= dict(score_threshold=float(score_threshold), score_ratio=float(score_ratio))
        self.predict_margin = int(predict_margin)
        self.max_total_fraction = cfg.max_total_fraction
        self.previous: np.ndarray | None = None  # low-resolution mask of the previous frame
        self._previous_tau: float | None = None
        self.timings_ms: list[float] = []
        self.last_debug: dict[str, np.ndarray] = {}

    def state_dict(self) -> dict:
        """The earlier frames (frame number, low-resolution depth, pose), the previous mask and its
        time: what the next frame is tested against."""
        return {
            "history": [(int(k), d.detach().cpu(), pose.detach().cpu()) for k, d, pose in self.history],
            "previous": None if self.previous is None else torch.from_numpy(self.previous.copy()),
            "previous_tau": self._previous_tau,
            "timings_ms": list(self.timings_ms),
        }

    def load_state_dict(self, state: dict) -> None:
        self.history = [(int(k), d, pose) for k, d, pose in state.get("history", [])]
        previous = state.get("previous")
        self.previous = None if previous is None else previous.numpy().copy()
        self._previous_tau = state.get("previous_tau")
        self.timings_ms = list(state.get("timings_ms", []))

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
        if low.sum() > self.max_total_fraction * max(int((dnp > 0).sum()), 1):
            # The camera is tracked on the static rest: a mask leaving less of it is the echo of a pose
            # error (flagged pixels track worse, which flags more), not a world that moved; carried on
            # it covered 97 % of static fr1 frames and lost 243 of 393.
            low = np.zeros_like(low)
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
        return upsample_mask(dilate(torch.from_numpy(self.previous), self.predict_margin), self.stride, frame.depth)

    def revise(self, keyframes: list, current, K: torch.Tensor) -> dict[int, torch.Tensor]:
        """The static-world test backwards: a keyframe's points that the current frame sees as free
        space have moved away since. With ``revise_lags`` = (a, b), keyframes a..b frames back are
        re-tested against the current frame and their masks grow by the cleaned result (never
        shrink), so the object is masked in them -- and in mapping -- even where it was still too
        slow to be caught when they were taken (``source='frames'`` only). Returns {frame id: grown mask}."""
        if self.source != "frames" or self.revise_lags is None:
            return {}
        s = self.stride
        lo, hi = self.revise_lags
        ref_depth = current.depth[::s, ::s]
        Kl = self._low_K(K)
        grown: dict[int, torch.Tensor] = {}
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
                grown[int(kf.frame_id)] = new
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

    def _map_seeds(
        self, frame: Frame, depth: torch.Tensor, context: MaskContext
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Residual seeds against the map ray-marched at the tracked pose, with the map's depth and
        where it knows a surface (all (h, w) at the low resolution)."""
        s = self.stride
        hs, ws = depth.shape
        uv = (pixel_grid(hs, ws, depth.device) * s).reshape(-1, 2)  # low-resolution pixel i is frame pixel i*s
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
