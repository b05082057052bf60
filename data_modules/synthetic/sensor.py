"""A switchable RGB-D sensor model applied to exact renders.

Depth parts (all off when ``depth_noise`` is False): lateral jitter, Kinect-like axial noise
``sigma(z) = axial * (0.0012 + 0.0019 (z - 0.4)^2)`` metres, quantisation, dropout along depth
discontinuities (edges) and at grazing angles, elliptical holes and sparse dropouts. Colour parts:
exposure (gain) drift, motion blur (the frame's colour averaged over the shutter at the times of
:func:`blur_offsets`: warped along the exact per-pixel motion by :func:`smear`, or, with
``blur_exact``, rendered at each time), additive noise, and 8-bit quantisation (always).

Each part draws from its own random stream keyed by (seed, frame, part), so switching one part on or
off, or changing its strength, leaves the realisation of every other part unchanged. A strength of 0
switches a part off.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F

from data_modules.sensor import kinect_depth_sigma

__all__ = ["SensorModel", "axial_sigma", "blur_offsets", "corrupt_depth", "corrupt_rgb", "exposure_gain", "part_rng", "smear"]

SENSOR_VERSION = 1
_PART_TAGS = {"axial": 1, "edges": 2, "grazing": 3, "holes": 4, "dropout": 5, "lateral": 6, "rgb": 7, "exposure": 8}


@dataclass(frozen=True)
class SensorModel:
    """Sensor switches and strengths (0 = off). Defaults: the Kinect-like model of the cube scene.

    Attributes:
        depth_noise: master switch of every depth part (False = exact depth).
        axial: scale of the axial noise sigma(z) (1 = Kinect-like).
        edge_dropout: probability of dropping a pixel in the band around depth discontinuities.
        grazing_dropout: probability of dropping a pixel seen at a grazing angle (|cos| < 0.12).
        holes: mean number of elliptical holes per frame (specularities, absorbing patches).
        dropout: probability of a sparse random dropout per pixel.
        lateral: sigma (pixels) of the lateral jitter: each pixel reads the depth of a neighbour at a
            random rounded offset, so silhouettes get ragged.
        quantization: depth step in metres (0.001 = millimetres).
        rgb_noise: sigma of additive Gaussian colour noise (colour in [0, 1]).
        exposure: amplitude of the smooth exposure drift (log gain; 0.15 = +-15 % brightness).
        motion_blur: colour samples averaged over the shutter (0 or 1 = no blur).
        shutter: shutter-open fraction of the frame period (motion blur length).
        blur_exact: render every blur sample (exact, also across occlusions, ``motion_blur`` times
            the render cost) instead of warping the frame along its per-pixel motion (fast; a moving
            object smears over what it covers, not over what it uncovers).
    """

    depth_noise: bool = True
    axial: float = 1.0
    edge_dropout: float = 0.6
    grazing_dropout: float = 0.5
    holes: float = 4.0
    dropout: float = 0.005
    lateral: float = 0.0
    quantization: float = 0.0
    rgb_noise: float = 0.01
    exposure: float = 0.0
    motion_blur: int = 0
    shutter: float = 0.5
    blur_exact: bool = False

    def problems(self) -> list[tuple[str, str]]:
        """(field, what is wrong) for every out-of-range value."""
        out = []
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("depth_noise", "blur_exact"):
                if not isinstance(v, bool):
                    out.append((f.name, f"must be true or false, got {v!r}"))
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                out.append((f.name, f"must be a finite number >= 0, got {v!r}"))
            elif f.name in ("edge_dropout", "grazing_dropout", "dropout", "shutter") and v > 1:
                out.append((f.name, f"must be within [0, 1], got {v!r}"))
            elif f.name == "rgb_noise" and v > 0.5:
                out.append((f.name, f"must be within [0, 0.5], got {v!r}"))
            elif f.name == "motion_blur" and (float(v) != int(v) or v > 32):
                out.append((f.name, f"must be an integer sample count in [0, 32], got {v!r}"))
        return out

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def part_rng(seed: int, frame: int, part: str) -> np.random.Generator:
    """The independent random stream of one sensor part for one frame."""
    return np.random.default_rng([int(seed), int(frame), SENSOR_VERSION, _PART_TAGS[part]])


def axial_sigma(z: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Kinect-like axial depth noise sigma (metres) at z-depth ``z`` (metres), scaled."""
    return scale * kinect_depth_sigma(z)


def _edge_band(z: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool: pixels within ``radius`` of a depth discontinuity (> 4 % relative jump)."""
    jump = np.zeros(z.shape, dtype=bool)
    dx = np.abs(np.diff(z, axis=1)) > 0.04 * z[:, 1:]
    dy = np.abs(np.diff(z, axis=0)) > 0.04 * z[1:, :]
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:, :] |= dy
    jump[:-1, :] |= dy
    # Square dilation by ``radius``, separably (rows, then columns).
    band = jump.copy()
    for k in range(1, radius + 1):
        band[:, k:] |= jump[:, :-k]
        band[:, :-k] |= jump[:, k:]
    rows = band.copy()
    for k in range(1, radius + 1):
        band[k:, :] |= rows[:-k, :]
        band[:-k, :] |= rows[k:, :]
    return band


def _lateral(z: np.ndarray, sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """Each pixel reads the depth at a random rounded offset (sigma ``sigma_px``, at most 3 sigma)."""
    H, W = z.shape
    lim = max(1, math.ceil(3 * sigma_px))
    du = np.clip(np.rint(rng.normal(0.0, sigma_px, (H, W))), -lim, lim).astype(np.int64)
    dv = np.clip(np.rint(rng.normal(0.0, sigma_px, (H, W))), -lim, lim).astype(np.int64)
    vv, uu = np.mgrid[0:H, 0:W]
    return z[np.clip(vv + dv, 0, H - 1), np.clip(uu + du, 0, W - 1)]


def _holes(shape: tuple[int, int], mean_count: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool union of a Poisson number of random ellipses (0.6-2.5 % of the width)."""
    H, W = shape
    hole = np.zeros(shape, dtype=bool)
    for _ in range(int(rng.poisson(mean_count))):
        cu, cv = rng.uniform(0, W), rng.uniform(0, H)
        ru, rv = rng.uniform(0.006, 0.025, size=2) * W
        # Only the ellipse's bounding box is evaluated.
        v0, v1 = max(0, int(cv - rv)), min(H, int(cv + rv) + 2)
        u0, u1 = max(0, int(cu - ru)), min(W, int(cu + ru) + 2)
        vv, uu = np.mgrid[v0:v1, u0:u1]
        hole[v0:v1, u0:u1] |= ((uu - cu) / ru) ** 2 + ((vv - cv) / rv) ** 2 <= 1.0
    return hole


def corrupt_depth(depth: np.ndarray, cos: np.ndarray, model: SensorModel, seed: int, frame: int) -> np.ndarray:
    """Sensor depth from exact depth.

    Args:
        depth: (H, W) float64 exact z-depth, metres.
        cos: (H, W) |cos| of the incidence angle of each pixel's ray.
        model: the sensor switches; seed, frame: key the random streams.
    Returns:
        (H, W) float64 metres, 0 = no measurement.
    """
    if not model.depth_noise:
        return depth.copy()
    H, W = depth.shape
    z = _lateral(depth, model.lateral, part_rng(seed, frame, "lateral")) if model.lateral > 0 else depth
    if model.axial > 0:
        z = z + axial_sigma(z, model.axial) * part_rng(seed, frame, "axial").standard_normal((H, W))
    if model.quantization > 0:
        z = np.rint(z / model.quantization) * model.quantization
    hole = np.zeros((H, W), dtype=bool)
    if model.edge_dropout > 0:
        band = _edge_band(depth, max(1, round(W / 320)))
        hole |= band & (part_rng(seed, frame, "edges").random((H, W)) < model.edge_dropout)
    if model.grazing_dropout > 0:
        hole |= (cos < 0.12) & (part_rng(seed, frame, "grazing").random((H, W)) < model.grazing_dropout)
    if model.holes > 0:
        hole |= _holes((H, W), model.holes, part_rng(seed, frame, "holes"))
    if model.dropout > 0:
        hole |= part_rng(seed, frame, "dropout").random((H, W)) < model.dropout
    return np.where(hole, 0.0, np.clip(z, 0.0, None))


def exposure_gain(t: float, model: SensorModel, seed: int) -> float:
    """Colour gain at time ``t`` s: a smooth, seeded drift ``exp(exposure * (two slow sines))``."""
    if model.exposure <= 0:
        return 1.0
    ph = np.random.default_rng([int(seed), SENSOR_VERSION, _PART_TAGS["exposure"]]).uniform(0, 2 * math.pi, 2)
    return math.exp(model.exposure * (0.7 * math.sin(2 * math.pi * 0.31 * t + ph[0]) + 0.3 * math.sin(2 * math.pi * 0.83 * t + ph[1])))


def blur_offsets(model: SensorModel, fps: float) -> list[float]:
    """Time offsets (s) of the colour samples averaged for motion blur, centred on the frame time
    ([] without blur): ``motion_blur`` samples evenly over ``shutter / fps`` seconds."""
    n = int(model.motion_blur)
    if n <= 1 or model.shutter <= 0:
        return []
    span = model.shutter / fps
    return [span * ((k + 0.5) / n - 0.5) for k in range(n)]


def smear(rgb: torch.Tensor, flows: list[torch.Tensor]) -> torch.Tensor:
    """Motion blur by backward warping: the mean of ``rgb`` sampled at ``x - flow(x)`` for each flow.

    Args:
        rgb: (H, W, 3) float32 sharp colour at the frame time.
        flows: (H, W, 2) float32 pixel displacements (du, dv) of each pixel's surface point from the
            frame time to each blur sample's time (what pixel x shows then is what was at x - flow).
    Returns:
        (H, W, 3) float32.
    """
    H, W, _ = rgb.shape
    img = rgb.permute(2, 0, 1)[None].expand(len(flows), 3, H, W)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    flow = torch.stack(flows)
    grid = torch.stack([2 * (u - flow[..., 0]) / max(W - 1, 1) - 1, 2 * (v - flow[..., 1]) / max(H - 1, 1) - 1], dim=-1)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.mean(0).permute(1, 2, 0).contiguous()


def corrupt_rgb(rgb: torch.Tensor, t: float, model: SensorModel, seed: int, frame: int) -> torch.Tensor:
    """Camera colour from noise-free (possibly already blurred) colour.

    Args:
        rgb: (H, W, 3) float32 in [0, 1].
        t: frame time in seconds (for the exposure drift).
    Returns:
        (H, W, 3) uint8: gain, additive noise, clamp, 8-bit quantisation.
    """
    gain = exposure_gain(t, model, seed)
    if gain != 1.0:
        rgb = rgb * gain
    if model.rgb_noise > 0:
        noise = part_rng(seed, frame, "rgb").standard_normal(tuple(rgb.shape), dtype=np.float32)
        rgb = rgb + torch.from_numpy(noise * np.float32(model.rgb_noise))
    return (rgb.clamp(0, 1) * 255.0).round().to(torch.uint8)
