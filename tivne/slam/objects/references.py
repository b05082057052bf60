"""An object's keyframe observations (references) and which of them a new view is aligned to."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tivne.slam.tracking.pyramid import PyramidLevel


@dataclass
class Reference:
    """An object's keyframe observation: its pyramid (object pixels only), camera-to-object pose,
    field time and number of object pixels."""

    pyramid: list[PyramidLevel]
    C: torch.Tensor
    tau: float
    pixels: int = 0



def view_direction(C: torch.Tensor) -> torch.Tensor:
    """(3,) unit direction from the object origin to the camera of camera-to-object pose C (4, 4)."""
    return C[:3, 3] / C[:3, 3].norm().clamp_min(1e-9)


def pick_reference(references: list[Reference], C_pred: torch.Tensor, max_angle_deg: float) -> Reference:
    """The oldest keyframe that saw the object from within ``max_angle_deg`` of the predicted view
    and from a distance within 25 %, else the newest: tracking against the oldest usable view, not
    a chain of the latest ones, keeps the object's drift from growing with every new keyframe."""
    d_pred, dist_pred = view_direction(C_pred), float(C_pred[:3, 3].norm())
    cos_max = float(np.cos(np.radians(max_angle_deg)))
    for ref in references[:-1]:
        ratio = float(ref.C[:3, 3].norm()) / max(dist_pred, 1e-9)
        if float(view_direction(ref.C) @ d_pred) >= cos_max and 0.8 <= ratio <= 1.25:
            return ref
    return references[-1]


def shows_enough(pixels: int, distance: float, ref: Reference, share: float = 0.5) -> bool:
    """Whether a view of ``pixels`` object pixels from ``distance`` (m) shows at least ``share`` of
    what ``ref`` showed, scaled to that distance (an object twice as far covers a quarter of the
    pixels): less means it is cut by the border or occluded."""
    ratio = float(ref.C[:3, 3].norm()) / max(distance, 1e-9)
    return pixels >= share * ref.pixels * ratio**2
