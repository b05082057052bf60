"""One rigid object's trajectory: object-to-world poses T_wo(τ) at the times it was observed,
interpolated on SE(3) between them (the interface the object fields and meshes read).

Conventions: a pose is (4, 4) float64 object-to-world, "c2w-style": x_world = T_wo(τ) · x_obj, so an
object field is queried at x_obj = T_wo(τ)⁻¹ x_world. τ is the field time of
the run's :class:`tivne.field.clock.Clock` (seconds since the first frame times ``time_scale``).
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from data_modules.poses import TIME_TOLERANCE_S, VELOCITY_BASELINE_S, pose_on_track

# τ closer than this to an observed τ is that observation (repeated adds replace it).
TAU_TOLERANCE = 1e-9
MAX_CACHED_TIMES = 4096  # pose_at's cache is dropped beyond this many times (e.g. a long 4D mesh sequence)


def _pose64(pose: torch.Tensor | np.ndarray) -> torch.Tensor:
    T = torch.as_tensor(pose, dtype=torch.float64).detach().cpu()
    if T.shape != (4, 4) or not bool(torch.isfinite(T).all()):
        raise ValueError(f"an object pose must be a finite (4, 4) matrix, got shape {tuple(T.shape)}")
    return T


def run_velocity(taus: list[float], seconds: Mapping[float, float], max_gap: float) -> tuple[bool, bool]:
    """Of a track observed at the increasing field times ``taus`` (``seconds``: τ -> its frame's time):
    whether it has an end velocity (its last two views at most ``max_gap`` seconds apart), and whether
    :meth:`ObjectTrack.pose_at` reads that velocity within its last run of views (none more than
    ``max_gap`` after the one before): the run is the whole track or spans more than
    VELOCITY_BASELINE_S. A shorter run after a gap has it read across the gap, an average over it,
    wrong for an object that turned back unseen. Walks back only that far (a few views)."""
    k = len(taus) - 1
    while k > 0 and seconds[taus[k]] - seconds[taus[k - 1]] <= max_gap:
        k -= 1
        if taus[-1] - taus[k] > VELOCITY_BASELINE_S + TIME_TOLERANCE_S:
            return True, True
    steady = k < len(taus) - 1
    return steady, steady and k == 0


class ObjectTrack:
    """The SE(3) trajectory of one object (id ``object_id``, dataset ``name`` when known).

    Attributes:
        object_id: the tracker's identity of the object (stable across leaving and re-entering).
        name: the dataset's name of the object (synthetic shape name, Co-Fusion id) or None.
        box: (2, 3) float64 [min, max] corners of the object's observed points in object
            coordinates, or None before any point was seen.
    """

    def __init__(self, object_id: int, name: str | None = None) -> None:
        self.object_id = int(object_id)
        self.name = name
        self.box: torch.Tensor | None = None
        self._taus: list[float] = []
        self._poses: list[torch.Tensor] = []
        # pose_at by τ: the object fields ask for the same few keyframe times on every query (each
        # interpolation costs ~1 ms in Python); cleared whenever an observation changes.
        self._at: dict[float, torch.Tensor] = {}

    @classmethod
    def from_poses(cls, object_id: int, taus, poses, name: str | None = None) -> "ObjectTrack":
        """A track from known poses (N,) τ and (N, 4, 4) object-to-world, e.g. the GT oracle."""
        track = cls(object_id, name)
        for tau, pose in zip(list(np.asarray(taus, dtype=np.float64)), torch.as_tensor(poses)):
            track.add(float(tau), pose)
        return track

    def __len__(self) -> int:
        return len(self._taus)

    @property
    def middle(self) -> torch.Tensor | None:
        """(3,) centre of :attr:`box` in object coordinates, or None before any point was seen."""
        return None if self.box is None else self.box.mean(0)

    def __repr__(self) -> str:
        span = f"τ {self._taus[0]:.3f}..{self._taus[-1]:.3f}" if self._taus else "empty"
        return f"ObjectTrack(id={self.object_id}, name={self.name!r}, {len(self)} poses, {span})"

    def add(self, tau: float, pose: torch.Tensor | np.ndarray) -> None:
        """Record the object-to-world pose (4, 4) observed at field time ``tau`` (kept sorted; an
        existing observation at the same τ is replaced)."""
        tau, T = float(tau), _pose64(pose)
        self._at.clear()
        i = int(np.searchsorted(np.asarray(self._taus), tau))
        for j in (i - 1, i):
            if 0 <= j < len(self._taus) and abs(self._taus[j] - tau) <= TAU_TOLERANCE:
                self._poses[j] = T
                return
        self._taus.insert(i, tau)
        self._poses.insert(i, T)

    def observed_taus(self) -> list[float]:
        """The field times with an observed pose, increasing."""
        return list(self._taus)

    def poses(self) -> torch.Tensor:
        """(N, 4, 4) float64 observed object-to-world poses in the order of :meth:`observed_taus`."""
        return torch.stack(self._poses) if self._poses else torch.zeros(0, 4, 4, dtype=torch.float64)

    def observed_near(self, tau: float, window: float) -> bool:
        """Whether an observation lies within ``window`` of ``tau`` (e.g. to place a mesh only
        where the object was seen around that time)."""
        tau = float(tau)
        i = bisect.bisect_left(self._taus, tau)  # the nearest observations are at i - 1 and i
        return any(abs(self._taus[j] - tau) <= window for j in (i - 1, i) if 0 <= j < len(self._taus))

    def pose_at(self, tau: float) -> torch.Tensor:
        """(4, 4) float64 object-to-world pose at field time ``tau``: SLERP rotation + linear
        translation of the box's :attr:`middle` between the bracketing observations; before the first / after the last
        observation the end pose continued at the end's velocity (:func:`data_modules.poses.pose_on_track`:
        an object entering or leaving the view keeps moving; readers place it only near an
        observation). Raises on an empty track."""
        if not self._taus:
            raise ValueError(f"object {self.object_id} has no observed pose")
        tau = float(tau)
        if tau not in self._at:
            if len(self._at) >= MAX_CACHED_TIMES:
                self._at.clear()
            self._at[tau] = pose_on_track(np.asarray(self._taus), torch.stack(self._poses), tau, pivot=self.middle)
        return self._at[tau].clone()

    def copy(self) -> ObjectTrack:
        """A copy that later observations of this track leave as it is (no pose is changed in place)."""
        out = ObjectTrack(self.object_id, self.name)
        out.box, out._taus, out._poses, out._at = self.box, list(self._taus), list(self._poses), dict(self._at)
        return out

    def grow_box(self, points_obj: torch.Tensor) -> None:
        """Extend :attr:`box` by (N, 3) points in object coordinates (non-finite rows ignored)."""
        p = torch.as_tensor(points_obj, dtype=torch.float64).detach().cpu().reshape(-1, 3)
        p = p[torch.isfinite(p).all(-1)]
        if len(p) == 0:
            return
        lo, hi = p.min(0).values, p.max(0).values
        if self.box is not None:
            lo, hi = torch.minimum(lo, self.box[0]), torch.maximum(hi, self.box[1])
        self.box = torch.stack([lo, hi])
        self._at.clear()  # poses between observations turn about the box's middle

    def state_dict(self) -> dict[str, Any]:
        return {
            "object_id": self.object_id,
            "name": self.name,
            "taus": torch.tensor(self._taus, dtype=torch.float64),
            "poses": self.poses(),
            "box": None if self.box is None else self.box.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.object_id, self.name = int(state["object_id"]), state["name"]
        self._taus = [float(t) for t in state["taus"]]
        self._poses = [_pose64(p) for p in state["poses"]]
        self._at.clear()
        self.box = None if state["box"] is None else torch.as_tensor(state["box"], dtype=torch.float64).clone()

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> "ObjectTrack":
        track = cls(int(state["object_id"]), state["name"])
        track.load_state_dict(state)
        return track
