"""The keyframe store (the one owner of keyframe poses) and window-selection policies (paper Eq. 11)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from tivne.config import KeyframeConfig
from tivne.render.rays import View
from tivne.render.samplers import sample_from_mask
from tivne.slam.tracking.overlap import overlap_ratios


@dataclass(frozen=True)
class Keyframe:
    """A stored keyframe's observation (its pose lives in the :class:`KeyframeStore`): rgb (H, W, 3)
    uint8 (the inputs are 8-bit anyway: a quarter of float32's memory), depth (H, W) metres, dynamic
    (H, W) bool or None, tau its field time."""

    frame_id: int
    tau: float
    rgb: torch.Tensor
    depth: torch.Tensor
    dynamic: torch.Tensor | None

    def colour(self) -> torch.Tensor:
        """(H, W, 3) float colour in [0, 1]."""
        return self.rgb.float() / 255.0

    @classmethod
    def of(cls, view: View) -> "Keyframe":
        rgb = view.rgb if view.rgb.dtype == torch.uint8 else (view.rgb.clamp(0, 1) * 255.0).round().to(torch.uint8)
        return cls(int(view.frame_id), float(view.tau), rgb, view.depth, view.dynamic)


class KeyframeStore:
    """The keyframes and the one owner of their (refined) poses.

    A keyframe is inserted every ``keyframe.every`` frames (frame 0 always), at most
    ``keyframe.max_stored`` of them: when the store is full, the keyframe whose removal leaves the
    smallest gap in time is dropped (never the first or the last), so the store keeps covering the
    whole sequence evenly, ever more sparsely, and memory stays bounded. Poses change only through
    :meth:`update_poses` (mapping's pose refinement, a pose-graph back end).
    """

    def __init__(self, cfg: KeyframeConfig = KeyframeConfig()) -> None:
        self.cfg = cfg
        self.records: list[Keyframe] = []
        self._poses: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.records)

    def should_insert(self, stream_index: int) -> bool:
        return stream_index % self.cfg.every == 0

    def add(self, view: View) -> list[tuple[int, torch.Tensor]]:
        """Store ``view`` as a keyframe at ``view.pose``; returns (frame id, final pose) of the
        keyframes dropped to make room (their poses will not change any more)."""
        self.records.append(Keyframe.of(view))
        self._poses[int(view.frame_id)] = view.pose.detach()
        dropped = []
        while len(self.records) > self.cfg.max_stored:
            ids = self.frame_ids()
            gaps = [ids[i + 1] - ids[i - 1] for i in range(1, len(ids) - 1)]  # the gap left without keyframe i
            gone = self.records.pop(1 + gaps.index(min(gaps)))
            dropped.append((gone.frame_id, self._poses.pop(gone.frame_id)))
        return dropped

    def update_poses(self, poses: Mapping[int, torch.Tensor]) -> None:
        """Replace the poses of the given keyframes ({frame id: (4, 4) c2w}); ids not stored are ignored."""
        for frame_id, pose in poses.items():
            if int(frame_id) in self._poses:
                self._poses[int(frame_id)] = pose.detach().to(self._poses[int(frame_id)].dtype)

    def set_masks(self, masks: Mapping[int, torch.Tensor]) -> None:
        """Replace the motion masks of the given keyframes ({frame id: (H, W) bool})."""
        for i, rec in enumerate(self.records):
            if rec.frame_id in masks:
                self.records[i] = dataclasses.replace(rec, dynamic=masks[rec.frame_id])

    def pose(self, frame_id: int) -> torch.Tensor:
        return self._poses[int(frame_id)]

    def pose_map(self) -> dict[int, torch.Tensor]:
        """{frame id: (4, 4) c2w} of every stored keyframe."""
        return dict(self._poses)

    def poses(self) -> torch.Tensor:
        """(K, 4, 4) current keyframe poses, in store order."""
        return torch.stack([self._poses[r.frame_id] for r in self.records])

    def frame_ids(self) -> list[int]:
        return [r.frame_id for r in self.records]

    def view(self, i: int) -> View:
        """The ``i``-th keyframe as the map sees it (uint8 colour, its current pose)."""
        r = self.records[i]
        return View(r.frame_id, r.tau, r.rgb, r.depth, r.dynamic, self._poses[r.frame_id])

    def views(self) -> list[View]:
        return [self.view(i) for i in range(len(self.records))]

    def state_dict(self) -> dict:
        """The stored keyframes as they are (uint8 colour, depth, masks, refined poses, frame ids)."""
        return {"views": [view_state(v) for v in self.views()]}

    def load_state_dict(self, state: dict) -> None:
        views = [view_from_state(v) for v in state["views"]]
        self.records = [Keyframe.of(v) for v in views]
        self._poses = {int(v.frame_id): v.pose for v in views}


def view_state(view: View) -> dict:
    """A :class:`View` as plain tensors and numbers (for a checkpoint)."""
    return {"frame_id": int(view.frame_id), "tau": float(view.tau), "rgb": view.rgb.detach(), "depth": view.depth.detach(),
            "dynamic": None if view.dynamic is None else view.dynamic.detach(), "pose": view.pose.detach()}


def view_from_state(state: dict) -> View:
    return View(int(state["frame_id"]), float(state["tau"]), state["rgb"], state["depth"], state["dynamic"], state["pose"])


@dataclass(frozen=True)
class KeyframePolicy:
    """Picks up to ``cfg.window`` keyframes for a mapping round.

    ``overlap``: the lowest reprojection overlap with the current frame among keyframes that overlap
    it at all (ratio > ``min_overlap``), so the window covers the most novel views that still see
    part of the current scene; ``random``: uniformly at random (Vox-Fusion).
    """

    cfg: KeyframeConfig = KeyframeConfig()

    def select(
        self, store: KeyframeStore, current: View, K: torch.Tensor, generator: torch.Generator | None = None
    ) -> list[int]:
        """Indices into ``store`` (excluding a keyframe that *is* the current frame)."""
        candidates = [i for i, fid in enumerate(store.frame_ids()) if fid != current.frame_id]
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
        ratios = overlap_ratios(uv, current.depth.reshape(-1)[idx], K, current.pose, store.poses()[candidates], w, h)
        order = torch.argsort(ratios)
        picked = [candidates[i] for i in order.tolist() if ratios[i] > self.cfg.min_overlap][: self.cfg.window]
        if not picked:  # nothing overlaps (e.g. tracking lost): fall back to the latest keyframes
            picked = candidates[-self.cfg.window :]
        return sorted(picked)
