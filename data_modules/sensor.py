"""Sensor models of RGB-D cameras: what the data layer knows about how depth is measured.

Consumers that reason about measurement noise (the synthetic sensor, geometric motion masks) take
the model from here so there is one definition of it.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

Depth = TypeVar("Depth", torch.Tensor, np.ndarray, float)

# (a, b, z0) of σ(z) = a + b (z − z0)², metres: Kinect v1 (Nguyen, Izadi and Lovell 2012).
KINECT_SIGMA: tuple[float, float, float] = (0.0012, 0.0019, 0.4)
# The Kinect's colour camera sits ~2.5 cm beside its IR (depth) camera (Khoshelham & Elberink, Sensors 2012).
KINECT_COLOUR_BASELINE_M = 0.025


def kinect_depth_sigma(z: Depth, coeffs: tuple[float, float, float] = KINECT_SIGMA) -> Depth:
    """Axial (along-ray) depth noise of a Kinect-like structured-light sensor, in metres.

    σ(z) = 0.0012 + 0.0019 (z − 0.4)², the fit of C. V. Nguyen, S. Izadi and D. Lovell, "Modeling
    Kinect Sensor Noise for Improved 3D Reconstruction and Tracking", 3DIMPVT 2012 (valid for
    surfaces seen at up to ~60° from the optical axis; the angle term is left out).

    Args:
        z: depth in metres, any shape (tensor, array or scalar).
        coeffs: (a, b, z0) of σ(z) = a + b (z − z0)², for another sensor's fit.
    Returns:
        σ with the shape and type of ``z``.
    """
    a, b, z0 = coeffs
    return a + b * (z - z0) ** 2
