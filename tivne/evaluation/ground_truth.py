"""What the evaluation needs of a dataset with exact geometry: the :class:`GroundTruth` protocol, and
small adapters from it to the numpy inputs of :mod:`tivne.metrics.surface`.

The protocol is structural: :class:`data_modules.synthetic.SyntheticSequence` satisfies it without
importing anything of ``tivne``; any other dataset that offers the same methods is evaluated the same
way. Everything is in the dataset's world frame (metres, seconds on the sequence clock).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
import torch

from data_modules.sequence import SequenceDataset, SequenceView
from tivne.metrics.surface import DistanceFn, OrientedBox


@runtime_checkable
class GroundTruth(Protocol):
    """A dataset with exact, time-varying geometry (checked with ``isinstance(ds, GroundTruth)``).

    Attributes:
        object_names: the moving objects.
    """

    object_names: list[str]

    def object_poses(self, t: float) -> dict[str, torch.Tensor]:
        """Object-to-world (4, 4) pose of every moving object at time ``t``."""
        ...

    def dynamic_box(self, t: float, name: str | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Oriented bounding box of object ``name`` at ``t``: center (3,), half extents (3,), R (3, 3)."""
        ...

    def sdf(self, points: torch.Tensor, t: float, part: str = "all") -> torch.Tensor:
        """Exact signed distance (N,) of (N, 3) points at ``t``; ``part``: "all", "static", "dynamic"."""
        ...

    def sample_surface(self, t: float, n: int, part: str = "all", seed: int = 0, name: str | None = None) -> torch.Tensor:
        """(n, 3) points uniform by area on the surface at ``t`` (``part``, or only object ``name``)."""
        ...

    def visible(self, points: torch.Tensor, t: float, window: float = 0.0, name: str | None = None) -> torch.Tensor:
        """(N,) bool: surface points at ``t`` (of object ``name``, None = static) that a camera of the
        sequence saw at a frame within ``window`` seconds of ``t``."""
        ...


def as_view(dataset: SequenceDataset) -> SequenceView:
    """The dataset as a :class:`SequenceView` (unchanged when it already is one)."""
    return dataset if isinstance(dataset, SequenceView) else SequenceView(dataset)


def ground_truth_of(view: SequenceView) -> GroundTruth | None:
    """The view's dataset when it has exact geometry, else None."""
    return view.base if isinstance(view.base, GroundTruth) else None


def object_box(gt: GroundTruth, t: float, name: str) -> OrientedBox:
    """Object ``name``'s oriented box at time ``t`` (float64 numpy)."""
    center, half, R = (np.asarray(torch.as_tensor(x, dtype=torch.float64)) for x in gt.dynamic_box(t, name))
    return OrientedBox(center, half, R)


def surface_distance(gt: GroundTruth, t: float, part: str = "all") -> DistanceFn:
    """Exact distance to the true surface at ``t``: ``|sdf(points, t, part)|`` as a numpy function."""

    def distance(points: np.ndarray) -> np.ndarray:
        if len(points) == 0:
            return np.zeros(0)
        return np.abs(np.asarray(gt.sdf(torch.from_numpy(np.asarray(points, dtype=np.float64)), t, part=part)))

    return distance


def surface_samples(gt: GroundTruth, t: float, n: int, part: str, seed: int, name: str | None = None) -> np.ndarray:
    """(n, 3) float64 samples of the true surface at ``t`` (see :meth:`GroundTruth.sample_surface`)."""
    return np.asarray(torch.as_tensor(gt.sample_surface(t, n, part=part, seed=seed, name=name), dtype=torch.float64))


def observed(gt: GroundTruth, points: np.ndarray, t: float, lo: float, hi: float, name: str | None = None) -> np.ndarray:
    """Which surface points at time ``t`` some camera saw at a time in ``[lo, hi]``.

    The dataset's :meth:`~GroundTruth.visible` takes a window centred on the points' time; to use an
    off-centre span (a window clipped to the frames a run processed), an object's points are first
    carried with the object from ``t`` to the span's centre.

    Args:
        points: (N, 3) world points on the surface at ``t`` (of object ``name``; None = static).
        lo, hi: seconds, ``lo <= hi``.
    Returns:
        (N,) bool.
    """
    if len(points) == 0 or hi < lo:
        return np.zeros(len(points), dtype=bool)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    p = torch.from_numpy(np.asarray(points, dtype=np.float64))
    if name is not None and centre != t:
        move = gt.object_poses(centre)[name].double() @ torch.linalg.inv(gt.object_poses(t)[name].double())
        p = p @ move[:3, :3].T + move[:3, 3]
    return np.asarray(gt.visible(p, centre, half, name), dtype=bool)
