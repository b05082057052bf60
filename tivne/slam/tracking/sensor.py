"""Sensor effects the dense odometry models: a rolling shutter's row times, and the parallax of colour
registered as if its camera shared the depth camera's centre."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tivne.geometry import invert_pose, se3_log


@dataclass(frozen=True)
class Shutter:
    """A rolling shutter: rows read out top to bottom over ``readout_s`` seconds, the frame's pose
    being the camera's at its middle row, so row v of an H-row image was seen (v − (H−1)/2)/H ·
    readout_s after it; ``velocity`` (6,) float64 is the camera's body twist (v, ω) per second then
    (c2w(t) = c2w · exp(t·velocity)). ``previous``: (4, 4) the frame before in the reference's frame,
    ``dt`` seconds earlier, from which :meth:`at` reads the velocity of a pose estimate instead."""

    readout_s: float
    velocity: torch.Tensor
    previous: torch.Tensor | None = None
    dt: float = 0.0

    def at(self, T: torch.Tensor) -> "Shutter":
        """With ``previous``: the shutter moving at the velocity from it to the estimate T (4, 4) T_ref_cur."""
        if self.previous is None or self.dt <= 0:
            return self
        return Shutter(self.readout_s, twist_per_second(self.previous.to(T), T, self.dt), self.previous, self.dt)

    def row_times(self, v: torch.Tensor, height: int) -> torch.Tensor:
        """(N,) seconds after the middle row at which rows v (N,) of an ``height``-row level were seen."""
        return (v - 0.5 * (height - 1)) * (self.readout_s / height)

    def motion(self, p: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        """(3, N) first-order displacement dt·(ω × p + v) of points p (3, N) in the camera's frame over dt (N,)."""
        xi = self.velocity.to(p)
        return dt * (torch.linalg.cross(xi[3:, None].expand_as(p), p, dim=0) + xi[:3, None])


def moving_shutter(readout_s: float, velocity: torch.Tensor | None) -> Shutter | None:
    """The shutter of a frame taken at ``velocity`` (6,), or None where its velocity is not known."""
    return None if velocity is None else Shutter(readout_s, velocity)


def frame_shutters(
    readout_s: float, velocity: torch.Tensor | None, *reference_velocities: torch.Tensor | None
) -> tuple[Shutter | None, ...]:
    """The ``shutters`` of :func:`~tivne.slam.tracking.odometry.track_pyramids` for a frame taken at
    ``velocity`` (6,) and its references taken at theirs (None where one is not known); () (a global
    shutter) where the frame's own velocity is not known."""
    if velocity is None:
        return ()
    return (Shutter(readout_s, velocity), *(moving_shutter(readout_s, v) for v in reference_velocities))


def twist_per_second(before: torch.Tensor, after: torch.Tensor, dt: float) -> torch.Tensor:
    """(6,) float64 body twist (v, ω) per second carrying c2w ``before`` to ``after`` (4, 4) in dt seconds."""
    return se3_log((invert_pose(before.double()) @ after.double())[None])[0] / dt


def parallax_pixels(z: torch.Tensor, focal: float, baseline: float) -> torch.Tensor:
    """(N,) pixels by which colour remapped as if its camera shared the depth camera's centre is off at
    depths z (N,) metres: f·b·|1/z − 1/z̃| for an unmodelled baseline b, z̃ the median depth (where a
    colour camera fitted to the frames is exact, its principal point absorbing the mean parallax)."""
    if z.numel() == 0:
        return z
    inverse = 1.0 / z.clamp_min(1e-3)
    return focal * baseline * (inverse - inverse.median()).abs()
