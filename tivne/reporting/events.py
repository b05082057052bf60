"""Scalar curves from a run's TensorBoard events (``tb/``: ``track/*``, ``map/*``, ``perf/*`` per frame)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_scalars(tb_dir: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every scalar tag in the events files of ``tb_dir``.

    Returns:
        {tag: (steps (N,) int64, values (N,) float64)}, sorted by step (a later file's value wins
        at a repeated step); {} when there are no events.
    """
    from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

    points: dict[str, dict[int, float]] = {}
    for path in sorted(Path(tb_dir).glob("events.out.tfevents.*")):
        events = EventAccumulator(str(path), size_guidance={SCALARS: 0})
        events.Reload()
        for tag in events.Tags()[SCALARS]:
            points.setdefault(tag, {}).update({int(e.step): float(e.value) for e in events.Scalars(tag)})
    out = {}
    for tag, by_step in points.items():
        steps = np.array(sorted(by_step), dtype=np.int64)
        out[tag] = (steps, np.array([by_step[s] for s in steps], dtype=np.float64))
    return out
