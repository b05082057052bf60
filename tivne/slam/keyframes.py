"""Keyframe database and window-selection policies (paper Eq. 11)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tivne.config import KeyframeConfig
from tivne.geometry import backproject, invert_pose, project, transform_points
from tivne.render.rays import View
from tivne.render.samplers import sample_from_mask


class KeyframeDatabase:
    """Keyframes inserted every ``every`` frames (frame 0 always), at most ``max_stored`` of them.

    Memory stays bounded on long sequences: a keyframe keeps its colour as uint8 (the inputs are
    8-bit anyway), and when the store is full the keyframe whose removal leaves the smallest gap in
    time is dropped (never the first or the last), so the store keeps covering the whole sequence
    evenly, ever more sparsely.
    """

    def __init__(self, every: int = 5, max_stored: int | None = None) -> None:
        self.every = int(every)
        self.max_stored = max_stored
        self.views: list[View] = []

    def __len__(self) -> int:
        return len(self.views)

    def should_insert(self, stream_index: int) -> bool:
        return stream_index % self.every == 0

    def add(self, view: View) -> list[View]:
        """Store ``view`` (the same object, its colour converted to uint8); returns the keyframes
        dropped to make room (their poses will not change any more)."""
        if view.rgb.dtype != torch.uint8:
            view.rgb = (view.rgb.clamp(0, 1) * 255.0).round().to(torch.uint8)
        self.views.append(view)
        dropped = []
        while self.max_stored is not None and len(self.views) > self.max_stored:
            ids = [v.frame_id for v in self.views]
            gaps = [ids[i + 1] - ids[i - 1] for i in range(1, len(ids) - 1)]  # the gap left without keyframe i
            dropped.append(self.views.pop(1 + gaps.index(min(gaps))))
        return dropped

    def poses(self) -> torch.Tensor:
        """(K, 4, 4) current keyframe poses."""
        return torch.stack([v.pose for v in self.views])

    def frame_ids(self) -> list[int]:
        return [v.frame_id for v in self.views]

    def state_dict(self) -> dict:
        """The stored views as they are (uint8 colour, depth, masks, refined poses, frame ids)."""
        return {"views": [view_state(v) for v in self.views]}

    def load_state_dict(self, state: dict) -> None:
        self.views = [view_from_state(v) for v in state["views"]]


def view_state(view: View) -> dict:
    """A :class:`View` as plain tensors and numbers (for a checkpoint)."""
    return {"frame_id": int(view.frame_id), "tau": float(view.tau), "rgb": view.rgb.detach(), "depth": view.depth.detach(),
            "dynamic": None if view.dynamic is None else view.dynamic.detach(), "pose": view.pose.detach()}


def view_from_state(state: dict) -> View:
    return View(int(state["frame_id"]), float(state["tau"]), state["rgb"], state["depth"], state["dynamic"], state["pose"])


def overlap_ratios(
    uv: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, kf_c2w: torch.Tensor, width: int, height: int
) -> torch.Tensor:
    """Share of the current frame's sampled pixels that reproject inside each keyframe (paper Eq. 11).

    u_kf = K · T_w2c(kf) · T_c2w(cur) · K⁻¹ · u, counted when it lands inside the image with positive depth.

    Args:
        uv: (N, 2) sampled pixels of the current frame; depth: (N,) their depths (> 0).
        K: (3, 3); c2w: (4, 4) current pose; kf_c2w: (F, 4, 4) keyframe poses.
    Returns:
        (F,) ratios in [0, 1].
    """
    world = transform_points(c2w, backproject(uv, depth, K))  # (N, 3)
    cam = transform_points(invert_pose(kf_c2w)[:, None], world[None])  # (F, N, 3)
    uv_kf, z = project(cam, K)
    inside = (z > 0) & (uv_kf[..., 0] >= 0) & (uv_kf[..., 0] <= width - 1) & (uv_kf[..., 1] >= 0) & (uv_kf[..., 1] <= height - 1)
    return inside.float().mean(dim=1)


@dataclass(frozen=True)
class KeyframePolicy:
    """Picks up to ``cfg.window`` keyframes for a mapping round.

    ``overlap``: the lowest reprojection overlap with the current frame among keyframes that overlap
    it at all (ratio > ``min_overlap``), so the window covers the most novel views that still see
    part of the current scene; ``random``: uniformly at random (Vox-Fusion).
    """

    cfg: KeyframeConfig = KeyframeConfig()

    def select(
        self, db: KeyframeDatabase, current: View, K: torch.Tensor, generator: torch.Generator | None = None
    ) -> list[int]:
        """Indices into ``db`` (excluding a keyframe that *is* the current frame)."""
        candidates = [i for i, v in enumerate(db.views) if v.frame_id != current.frame_id]
        if len(candidates) <= self.cfg.window:
            return candidates
        if self.cfg.policy == "random":
            perm = torch.randperm(len(candidates), generator=generator)[: self.cfg.window]
            return sorted(candidates[i] for i in perm.tolist())
        idx = sample_from_mask(current.depth > 0, self.cfg.overlap_pixels, generator)
        if idx.numel() == 0:
            return candidates[-self.cfg.window :]
        h, w = current.depth.shape
        uv = torch.stack([idx % w, idx // w], dim=-1).to(current.depth.dtype)
        ratios = overlap_ratios(uv, current.depth.reshape(-1)[idx], K, current.pose, db.poses()[candidates], w, h)
        order = torch.argsort(ratios)
        picked = [candidates[i] for i in order.tolist() if ratios[i] > self.cfg.min_overlap][: self.cfg.window]
        if not picked:  # nothing overlaps (e.g. tracking lost): fall back to the latest keyframes
            picked = candidates[-self.cfg.window :]
        return sorted(picked)
