"""Training losses (paper Eq. 6-10): colour, depth, free space, SDF and background offset."""

from __future__ import annotations

import torch

from tivne.config import LossWeights
from tivne.render.renderer import RenderBatch, RenderedRays


def balance_factors(n_free: torch.Tensor, n_trunc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """β_space = 1 - P_fs/(P_fs+P_tr), β_sdf = 1 - P_tr/(P_fs+P_tr): the majority class is down-weighted."""
    total = (n_free + n_trunc).clamp_min(1)
    return 1 - n_free / total, 1 - n_trunc / total


def routed_sdf(
    parts: torch.Tensor, dynamic: torch.Tensor, unsure: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which field a ray's SDF target supervises in a composition of a static field and objects.

    A ray on a moving object (``dynamic``) regresses the object fields' SDF where one is valid, a
    static ray the static field's; the other part only must not lie below the target (it may be
    free where the first one has the surface). Without this the min of the composition hands the
    target to whichever part is smaller, and a static copy of an object starves the object's own field.
    A ray whose label is ``unsure`` (along a mask's edge, where depth jitter mixes the labels) regresses
    the composition (the min) as before routing, so a wrong label pushes neither part.

    Args:
        parts: (N, M, 2) static / object SDF (object NaN where none is valid: the composition there
        is the static field); dynamic: (N,) bool ray label; unsure: (N,) bool or None (all sure).
    Returns:
        own (N, M): the SDF to regress; other (N, M): the SDF to keep above the target (NaN: none).
    """
    static, objects = parts[..., 0], parts[..., 1]
    moving = dynamic[:, None].expand_as(static)
    on_object = moving & ~torch.isnan(objects)
    own = torch.where(on_object, objects, static)  # a moving ray no object field covers: the static field, as the min
    other = torch.where(moving, static.masked_fill(~on_object, float("nan")), objects)
    if unsure is not None:
        unsure = unsure[:, None].expand_as(static)
        own = torch.where(unsure, torch.fmin(static, objects), own)  # fmin: the composition (NaN is "no object")
        other = other.masked_fill(unsure, float("nan"))
    return own, other


def sdf_losses(
    sdf: torch.Tensor, z: torch.Tensor, depth: torch.Tensor, truncation: float, ray_mask: torch.Tensor | None = None,
    parts: torch.Tensor | None = None, dynamic: torch.Tensor | None = None, unsure: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Free-space and SDF losses on samples.

    Samples with z < D - tr are free space (ŝ -> 1); samples with |z - D| <= tr regress
    ŝ·tr = D - z. Means run over all sample slots (as Vox-Fusion), weighted by β.

    Args:
        sdf: (N, M) truncation units; z: (N, M); depth: (N,) observed; ray_mask: (N,) bool rays to use.
        parts, dynamic: a composition's (N, M, 2) static / object SDF and the (N,) ray labels: the
            band then regresses the part :func:`routed_sdf` names and keeps the other above the target;
            unsure: (N,) bool rays whose label is not trusted (they regress the composition).
    Returns:
        (free_space_loss, sdf_loss) scalars.
    """
    d = depth[:, None]
    free = z < d - truncation
    trunc = (z - d).abs() <= truncation
    if ray_mask is not None:
        free = free & ray_mask[:, None]
        trunc = trunc & ray_mask[:, None]
    beta_fs, beta_tr = balance_factors(free.sum().float(), trunc.sum().float())
    slots = sdf.numel()
    fs = ((sdf - 1).pow(2) * free).sum() / slots
    if parts is None or dynamic is None:
        tr = ((z + sdf * truncation - d).pow(2) * trunc).sum() / slots
        return beta_fs * fs, beta_tr * tr
    own, other = routed_sdf(parts, dynamic, unsure)
    # How far the other part lies below the target (0 where it has none: NaN, masked before the arithmetic).
    below = torch.where(torch.isnan(other), torch.zeros_like(other), (d - z - other * truncation).clamp_min(0.0))
    tr = (((z + own * truncation - d).pow(2) + below.pow(2)) * trunc).sum() / slots
    return beta_fs * fs, beta_tr * tr


def robust_ray_mask(rendered: RenderedRays, depth: torch.Tensor, factor: float) -> torch.Tensor:
    """Reject rays whose depth residual exceeds ``factor`` x the batch median (tracking outliers,
    e.g. a moving object the frozen map has not seen yet). ``factor <= 0`` keeps every ray."""
    residual = (rendered.depth - depth).abs().detach()
    keep = rendered.weight_sum.detach() > 1e-6
    if factor > 0 and keep.any():
        keep = keep & (residual <= factor * residual[keep].median().clamp_min(1e-4))
    return keep


def slam_loss(
    batch: RenderBatch, truncation: float, weights: LossWeights, ray_mask: torch.Tensor | None = None,
    unsure: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss Eq. (6) of a rendered batch and its terms (detached) for logging.

    ``ray_mask`` (N,) bool: the rays to use (default: rays that rendered any weight). ``unsure`` (N,)
    bool: rays whose motion label the SDF routing does not trust (:func:`routed_sdf`).

    The offset term ‖Δe‖² runs over samples of background rays, only when the rays carry a motion
    mask: without one nothing is known to be static, so the deformation is left free.
    """
    rays, z, rendered, outputs = batch.rays, batch.z, batch.rendered, batch.outputs
    if ray_mask is None:
        ray_mask = rendered.weight_sum.detach() > 1e-6
    m = ray_mask.float()
    count = m.sum().clamp_min(1)
    color = ((rendered.rgb - rays.rgb).abs().mean(-1) * m).sum() / count
    depth = ((rendered.depth - rays.depth).abs() * m).sum() / count
    routed = (outputs.parts, rays.dynamic, unsure) if rays.has_mask else (None, None, None)
    free_space, sdf = sdf_losses(outputs.sdf, z, rays.depth, truncation, ray_mask, *routed)
    total = weights.color * color + weights.depth * depth + weights.free_space * free_space + weights.sdf * sdf
    terms = {"color": color, "depth": depth, "free_space": free_space, "sdf": sdf}
    if rays.has_mask and weights.offset > 0:
        background = (~rays.dynamic & ray_mask)[:, None] & outputs.valid
        offset = (outputs.offset_sq * background).sum() / background.sum().clamp_min(1)
        total = total + weights.offset * offset
        terms["offset"] = offset
    terms = {k: v.detach() for k, v in terms.items()}
    terms["total"] = total.detach()
    return total, terms
