"""Image metrics as pure functions: MSE, PSNR, SSIM (kornia) and LPIPS (offline only).

Inputs are torch tensors (or numpy arrays) of shape (H, W, 3) or (B, 3, H, W), float in [0, 1], with
an optional mask; computation is in torch on the input's device; results are python floats.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch

ArrayLike = np.ndarray | torch.Tensor




def _as_bchw(img: ArrayLike) -> torch.Tensor:
    """(H, W, 3) or (B, 3, H, W) -> (B, 3, H, W) float tensor (float64 stays float64)."""
    t = torch.as_tensor(img)
    if not t.is_floating_point():
        raise ValueError(f"image metrics need float images in [0, 1], got dtype {t.dtype}")
    if t.ndim == 3 and t.shape[-1] == 3:
        return t.permute(2, 0, 1)[None]
    if t.ndim == 4 and t.shape[1] == 3:
        return t
    raise ValueError(f"image metrics need (H, W, 3) or (B, 3, H, W) images, got shape {tuple(t.shape)}")


def _as_b1hw_mask(mask: ArrayLike | None, like: torch.Tensor) -> torch.Tensor | None:
    """(H, W), (B, H, W) or (B, 1, H, W) bool -> (B, 1, H, W) bool broadcastable against ``like``."""
    if mask is None:
        return None
    m = torch.as_tensor(mask, device=like.device).bool()
    if m.ndim == 2:
        m = m[None, None]
    elif m.ndim == 3:
        m = m[:, None]
    b, _, h, w = like.shape
    if m.ndim != 4 or m.shape[1] != 1 or m.shape[-2:] != (h, w) or m.shape[0] not in (1, b):
        raise ValueError(f"mask shape {tuple(torch.as_tensor(mask).shape)} does not fit images of shape {tuple(like.shape)}")
    return m.expand(b, 1, h, w)


def _pair(pred: ArrayLike, gt: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
    p, g = _as_bchw(pred), _as_bchw(gt)
    if p.shape != g.shape:
        raise ValueError(f"pred shape {tuple(p.shape)} != gt shape {tuple(g.shape)} (after layout to B,3,H,W)")
    g = g.to(device=p.device, dtype=p.dtype)
    return p, g


def _per_image_mse(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor | None) -> torch.Tensor:
    """(B,) mean squared error per image over valid pixels and channels (NaN where none are valid)."""
    sq = (p - g) ** 2
    if m is None:
        return sq.flatten(1).mean(1)
    w = m.to(sq.dtype).expand_as(sq)
    return (sq * w).flatten(1).sum(1) / w.flatten(1).sum(1)  # 0 / 0 = NaN for an empty mask


def mse(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None) -> float:
    """Mean squared error over all valid pixels, channels and images.

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        mask: optional (H, W), (B, H, W) or (B, 1, H, W) bool, True where the pixel counts.
    Returns:
        MSE; NaN when the mask selects no pixel.
    """
    p, g = _pair(pred, gt)
    m = _as_b1hw_mask(mask, p)
    sq = (p - g) ** 2
    if m is None:
        return float(sq.mean())
    w = m.to(sq.dtype).expand_as(sq)
    return float((sq * w).sum() / w.sum())


def psnr(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(max_val^2 / MSE)``.

    For a batch, the PSNR of every image is computed from its own MSE and the mean over images is
    returned (the usual per-frame averaging of neural SLAM evaluations).

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        mask: optional (H, W), (B, H, W) or (B, 1, H, W) bool, True where the pixel counts.
        max_val: peak signal value.
    Returns:
        PSNR in dB. ``math.inf`` when an image matches exactly (MSE = 0; not capped — write it as
        null in JSON); NaN when the mask selects no pixel in some image.
    """
    p, g = _pair(pred, gt)
    per_image = _per_image_mse(p, g, _as_b1hw_mask(mask, p)).double()
    vals = 10.0 * torch.log10(max_val**2 / per_image)  # mse = 0 -> +inf
    return float(vals.mean())


def ssim(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike | None = None, window_size: int = 11) -> float:
    """Structural similarity (Gaussian window, kornia.metrics.ssim, data range 1).

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        mask: optional (H, W), (B, H, W) or (B, 1, H, W) bool; when given, the SSIM map is averaged
            over the selected pixels only (windows still see their unmasked neighbours).
        window_size: Gaussian window size (odd).
    Returns:
        Mean SSIM in [-1, 1] (1 for identical images); NaN when the mask selects no pixel.
    """
    import kornia

    p, g = _pair(pred, gt)
    m = _as_b1hw_mask(mask, p)
    smap = kornia.metrics.ssim(p, g, window_size=window_size, max_val=1.0)  # (B, 3, H, W)
    if m is None:
        return float(smap.mean())
    w = m.to(smap.dtype).expand_as(smap)
    return float((smap * w).sum() / w.sum())


# Torchvision backbone files that LPIPS needs in the torch hub cache (never downloaded here).
_LPIPS_BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}


def lpips_available(net: str = "alex") -> tuple[bool, str]:
    """Whether :func:`lpips` can run offline.

    Needs the ``lpips`` and ``torchvision`` packages and the torchvision backbone weights already in
    the torch hub cache (``$TORCH_HOME/hub/checkpoints``); nothing is downloaded.

    Returns:
        (True, "") or (False, reason).
    """
    if net not in _LPIPS_BACKBONE_FILES:
        return False, f"unsupported LPIPS backbone {net!r} (use one of {sorted(_LPIPS_BACKBONE_FILES)})"
    try:
        import torchvision  # noqa: F401
    except Exception as e:  # ImportError, or a torchvision built for another torch
        return False, f"torchvision not importable ({type(e).__name__}: {e})"
    try:
        import lpips as _lpips  # noqa: F401
    except Exception as e:
        return False, f"lpips package not importable ({type(e).__name__}: {e})"
    weights = Path(torch.hub.get_dir()) / "checkpoints" / _LPIPS_BACKBONE_FILES[net]
    if not weights.is_file():
        return False, f"LPIPS backbone weights not in the local torch hub cache ({weights.name}); not downloading"
    return True, ""


@functools.lru_cache(maxsize=4)
def _lpips_model(net: str, device: str) -> torch.nn.Module:
    import lpips as _lpips

    # The backbone weights are in the hub cache (checked by lpips_available), so torchvision loads
    # them from disk; the linear calibration layers ship inside the lpips package.
    model = _lpips.LPIPS(net=net, verbose=False).eval().to(device)
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def lpips(pred: ArrayLike, gt: ArrayLike, net: str = "alex") -> tuple[float | None, str]:
    """Learned perceptual image patch similarity (lower is better), averaged over the batch.

    Args:
        pred, gt: (H, W, 3) or (B, 3, H, W) float in [0, 1].
        net: backbone, "alex" (default, as most neural SLAM papers) or "vgg".
    Returns:
        (value, "") or (None, reason) when :func:`lpips_available` says it cannot run offline.
    """
    ok, reason = lpips_available(net)
    if not ok:
        return None, reason
    p, g = _pair(pred, gt)
    model = _lpips_model(net, str(p.device))
    with torch.no_grad():
        d = model(p.float() * 2 - 1, g.float() * 2 - 1)  # LPIPS expects [-1, 1]
    return float(d.mean()), ""
