"""The field's clock: sequence time (seconds) to field time τ, the one place τ is computed."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Clock:
    """τ = (t - t0) · scale: 0 on the first frame, never normalised by the sequence length (it is
    unknown online). ``t0`` is the first frame's timestamp (seconds), ``scale`` is ``field.time_scale``."""

    t0: float
    scale: float = 1.0

    def tau(self, timestamp: float) -> float:
        return (float(timestamp) - self.t0) * self.scale

    def state_dict(self) -> dict[str, float]:
        return {"t0": self.t0, "scale": self.scale}

    @classmethod
    def from_state(cls, state: dict[str, float]) -> "Clock":
        return cls(float(state["t0"]), float(state["scale"]))
