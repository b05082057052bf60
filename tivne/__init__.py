"""TivNe: dynamic dense RGB-D SLAM with a time-varying neural field."""

__version__ = "0.1.0"
