"""Stage 2 of the render path: which pixels become rays (pixel samplers) and where the samples go
along them (depth-guided placement)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tivne.config import RenderConfig, SamplerConfig
from tivne.morphology import edge_band, edge_band_at


def sample_from_mask(mask: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Draw ``n`` flat pixel indices uniformly, with replacement, from the True pixels of ``mask``.

    Args:
        mask: (H, W) bool.
    Returns:
        (n,) int64 flat indices; empty when the mask has no True pixel.
    """
    return draw(mask.reshape(-1).nonzero()[:, 0], n, generator)


def draw(candidates: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(C,) candidate indices -> (n,) drawn uniformly with replacement (empty if C == 0)."""
    if candidates.numel() == 0 or n <= 0:
        return candidates[:0]
    pick = torch.randint(candidates.numel(), (n,), generator=generator).to(candidates.device)
    return candidates[pick]


@dataclass
class PixelPool:
    """Flat indices of a frame's usable pixels, computed once and drawn from every iteration.

    valid: (Nv,) pixels with depth; dynamic / static: (Nd,) / (Ns,) split of them by the motion
    mask (dynamic empty and static = valid without a mask); labels: the (H, W) motion mask, or None
    (no mask, or nothing on it moves); label_edge: a label within this many pixels of the mask's edge
    is not trusted (0: all are).
    """

    valid: torch.Tensor
    dynamic: torch.Tensor
    static: torch.Tensor
    labels: torch.Tensor | None = None
    label_edge: int = 0

    @classmethod
    def from_masks(cls, valid: torch.Tensor, dynamic: torch.Tensor | None, edge: int = 0, label_edge: int = 0) -> "PixelPool":
        """valid, dynamic: (H, W) bool; ``edge``: leave out the pixels within that many pixels of the
        dynamic mask's edge (:func:`edge_band`); ``label_edge``: their labels are unsure within that many."""
        if dynamic is not None and edge > 0:
            valid = valid & ~edge_band(dynamic, edge)
        flat_valid = valid.reshape(-1)
        all_idx = flat_valid.nonzero()[:, 0]
        if dynamic is None:
            return cls(all_idx, all_idx[:0], all_idx)
        dyn = dynamic.reshape(-1)[all_idx]
        labels = dynamic if label_edge > 0 and bool(dynamic.any()) else None  # no edge: every label is sure
        return cls(all_idx, all_idx[dyn], all_idx[~dyn], labels, label_edge)

    def is_unsure(self, pixels: torch.Tensor) -> torch.Tensor:
        """(n,) flat pixel indices -> (n,) bool: whether each one's label is unsure (:func:`edge_band_at`)."""
        if self.labels is None:
            return torch.zeros_like(pixels, dtype=torch.bool)
        return edge_band_at(self.labels, pixels, self.label_edge)


@dataclass(frozen=True)
class PixelSampler:
    """Chooses pixels with valid depth; ``cfg.dynamic_share`` of them from dynamic (masked) pixels.

    ``dynamic_share = 0`` is the ``uniform`` sampler; ``mask_weighted`` over-samples moving objects so
    the field learns them from the few pixels they cover. Without a mask (or with no dynamic pixel
    in view) every ray is drawn uniformly.
    """

    cfg: SamplerConfig = SamplerConfig(name="uniform", dynamic_share=0.0)

    @property
    def dynamic_share(self) -> float:
        return self.cfg.dynamic_share

    def __call__(self, pool: PixelPool, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """-> (n,) flat pixel indices (empty only when the frame has no valid pixel)."""
        if self.dynamic_share > 0 and pool.dynamic.numel() > 0 and pool.static.numel() > 0:
            n_dyn = int(round(n * self.dynamic_share))
            return torch.cat([draw(pool.dynamic, n_dyn, generator), draw(pool.static, n - n_dyn, generator)])
        return draw(pool.valid, n, generator)


def depth_guided_depths(
    depth: torch.Tensor,
    truncation: float,
    n_band: int,
    n_free: int,
    band: float = 2.0,
    near: float = 0.05,
    stratified: bool = True,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Sample z-depths along rays around the observed depth.

    ``n_band`` stratified samples in [D - band*tr, D + band*tr] plus ``n_free`` stratified samples in
    free space [near, D - band*tr] (empty when the band reaches the near plane: then all free
    samples collapse onto ``near`` and are cheap invalid points).

    Args:
        depth: (N,) observed z-depth, all > 0.
    Returns:
        (N, n_free + n_band) ascending z values.
    """
    n = depth.shape[0]
    half = band * truncation
    lo = (depth - half).clamp_min(near)

    def strata(count: int) -> torch.Tensor:
        base = torch.arange(count, device=depth.device, dtype=depth.dtype)
        if stratified:
            jitter = torch.rand(n, count, generator=generator, dtype=depth.dtype).to(depth.device)
        else:
            jitter = torch.full((n, count), 0.5, device=depth.device, dtype=depth.dtype)
        return (base + jitter) / count  # (N, count) in (0, 1)

    band_z = lo[:, None] + (depth + half - lo)[:, None] * strata(n_band)
    if n_free == 0:
        return band_z
    free_z = near + (lo - near).clamp_min(0)[:, None] * strata(n_free)
    return torch.cat([free_z, band_z], dim=1)


def place_samples(
    depth: torch.Tensor, cfg: RenderConfig, stratified: bool, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Depth-guided samples for rays with observed ``depth`` (N,) -> (N, n_free + n_band) ascending z,
    as configured by ``cfg`` (see :func:`depth_guided_depths`)."""
    return depth_guided_depths(depth, cfg.truncation, cfg.n_band, cfg.n_free, cfg.band, cfg.near, stratified, generator)
