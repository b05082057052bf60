"""The colour camera of an RGB-D sensor whose colour is not registered to its depth, from the frames.

Model (what ``dataset.colour_camera`` and ``dataset.colour_offset`` apply, :mod:`data_modules.tum`):
the colour pixel of a depth pixel with normalised coordinates n = K⁻¹(u, v, 1) and depth Z is
(fx (n_x − o_x/Z) + cx, fy (n_y − o_y/Z) + cy), where o is the colour camera's centre in the depth
camera's frame (the two cameras' axes taken as parallel; o from the rig's calibration). Without o the
centres are one and the model is the homography K_colour K⁻¹: a baseline's parallax at the scene's
usual depth then goes into the principal point and is wrong by fx·o/Z elsewhere.

Estimate, with no pose and no calibration target: a depth discontinuity is an object's silhouette,
and a silhouette is almost always a colour edge too. Over frames spread through the sequence, the
colour camera is the one that puts the most colour-gradient energy on the near side of the depth
edges: a search over a common focal scale (colour cameras differ from their depth camera mostly
there; tens of pixels at the image border, beyond any local method's basin), then Nelder–Mead over
(fx, fy, cx, cy), within the searched focal range and the middle fifth of the image for the
principal point. On a registered sequence (TUM fr1) it returns the depth camera within ~1 %; that
is its accuracy, so it is for colour that is clearly not registered (7-Scenes: 10 % off).

The offset is not estimated here. Fitting o_x as a fifth parameter was measured: on 7-Scenes it finds
3.5–3.7 cm (a Kinect-like baseline; edge contrast 1.96 → 2.15), but on synthetic scenes it is not
identifiable from edges alone (registered colour: up to 2.3 cm found; a true 4 cm: 0.1–3.1 cm found).
With that fit on the 7-Scenes tail (o = (3.48, −0.26) cm, colour camera refitted) the camera ATE of a
tracking-only run went 2.674 → 2.598 cm: a small gain, and the bench does not use a value fitted to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from data_modules.frame import Intrinsics

FOCAL_SCALES = tuple(0.8 + 0.025 * i for i in range(17))


@dataclass(frozen=True)
class EdgeFrame:
    """One frame's evidence: strength (H, W) float32, the colour gradient magnitude (smoothed, mean 1);
    n (2, N) normalised depth-camera coordinates of the near-side depth-edge pixels."""

    strength: np.ndarray
    n: np.ndarray


@dataclass(frozen=True)
class ColourCameraEstimate:
    """colour_camera (fx, fy, cx, cy); contrast_registered / contrast_estimated: the mean colour-edge
    strength on the depth edges (1 = an average pixel) with colour taken as registered and with the
    estimate; frames and depth-edge pixels used."""

    colour_camera: tuple[float, float, float, float]
    contrast_registered: float
    contrast_estimated: float
    frames: int
    edge_pixels: int


def colour_maps(intrinsics: Intrinsics, colour_camera: tuple[float, ...], distortion: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (H, W) float32 x, y: for each depth pixel, its pixel in the colour image of
    camera (fx, fy, cx, cy) = ``colour_camera`` with ``distortion`` (k1 k2 p1 p2 [k3]; None = none)."""
    K = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1.0]])
    fx, fy, cx, cy = colour_camera
    Kc = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    dist = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    return cv2.initUndistortRectifyMap(Kc, dist, None, K, (intrinsics.width, intrinsics.height), cv2.CV_32FC1)


def with_parallax(maps: tuple[np.ndarray, np.ndarray], depth: np.ndarray, colour_camera: tuple[float, ...],
                  offset: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """``maps`` (:func:`colour_maps`, (H, W) x, y each) moved by each depth pixel's parallax
    (−fx o_x/Z, −fy o_y/Z) for depth (H, W) metres; a pixel without depth takes the parallax at the
    frame's median depth (none if the frame has no depth). The shift is added after the colour
    camera's distortion, which is exact without one and first order with one."""
    valid = depth > 0
    if not valid.any():
        return maps
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 1.0 / float(np.median(depth[valid]))).astype(np.float32)
    return maps[0] - np.float32(colour_camera[0] * offset[0]) * inv, maps[1] - np.float32(colour_camera[1] * offset[1]) * inv


def edge_frame(rgb: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, smooth_px: float = 1.5) -> EdgeFrame:
    """The evidence of one frame: rgb (H, W, 3) in [0, 1], depth (H, W) metres (0 = invalid).

    A near-side edge pixel has a 4-neighbour farther by more than 5 cm + 3 % of its depth (beyond the
    sensor's noise, so a real silhouette).
    """
    luma = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    luma = cv2.GaussianBlur(luma, (0, 0), smooth_px)
    strength = np.hypot(cv2.Sobel(luma, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(luma, cv2.CV_32F, 0, 1, ksize=3))
    strength = strength / max(float(strength.mean()), 1e-12)
    valid = depth > 0
    far = np.where(valid, depth, np.inf)
    near = np.zeros_like(valid)
    for shift in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        near |= valid & ((np.roll(far, shift, axis=(0, 1)) - depth) > 0.05 + 0.03 * depth)
    near[[0, -1], :] = near[:, [0, -1]] = False  # np.roll wraps around the border
    v, u = np.nonzero(near)
    n = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy]).astype(np.float64)
    return EdgeFrame(strength.astype(np.float32), n)


def edge_contrast(frames: list[EdgeFrame], camera: np.ndarray) -> float:
    """Mean colour-edge strength at the depth-edge pixels mapped through camera (4,) = (fx, fy, cx, cy)
    (0 outside the image), averaged over frames."""
    total = 0.0
    for f in frames:
        x = (camera[0] * f.n[0] + camera[2]).astype(np.float32)[None]
        y = (camera[1] * f.n[1] + camera[3]).astype(np.float32)[None]
        total += float(cv2.remap(f.strength, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0).mean())
    return total / max(len(frames), 1)


def estimate_colour_camera(frames: list[EdgeFrame], intrinsics: Intrinsics, focal_scales: tuple[float, ...] = FOCAL_SCALES) -> ColourCameraEstimate:
    """The colour camera (module docstring) from :func:`edge_frame` evidence of a depth camera ``intrinsics``.

    Raises ValueError when the frames have no depth edges (nothing to register by).
    """
    from scipy.optimize import minimize

    edges = sum(f.n.shape[1] for f in frames)
    if edges == 0:
        raise ValueError("no depth edges in the frames: the colour camera cannot be estimated from them")
    depth_camera = np.array([intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy], dtype=np.float64)
    best = max(focal_scales, key=lambda s: edge_contrast(frames, depth_camera * [s, s, 1.0, 1.0]))
    start = depth_camera * [best, best, 1.0, 1.0]
    f_step, c_step = 0.03 * start[0], 0.01 * intrinsics.width  # the search's grain, then a few pixels
    simplex = np.array([start, start + [f_step, 0, 0, 0], start + [0, f_step, 0, 0], start + [0, 0, c_step, 0], start + [0, 0, 0, c_step]])
    lo, hi = min(focal_scales), max(focal_scales)
    bounds = [(lo * intrinsics.fx, hi * intrinsics.fx), (lo * intrinsics.fy, hi * intrinsics.fy),
              (0.4 * intrinsics.width, 0.6 * intrinsics.width), (0.4 * intrinsics.height, 0.6 * intrinsics.height)]
    found = minimize(lambda c: -edge_contrast(frames, c), start, method="Nelder-Mead", bounds=bounds,
                     options=dict(initial_simplex=simplex, xatol=0.05, fatol=1e-5, maxiter=400))
    camera = tuple(float(v) for v in found.x)
    return ColourCameraEstimate(camera, edge_contrast(frames, depth_camera), -float(found.fun), len(frames), edges)
