"""The one number a run reports to a sweeper (``hydra/sweeper=optuna`` minimises it), from its metrics.

A metric the run could not compute is never replaced by a number (a made-up value would look like a
result to the optimiser); the value is then None with the reason, and the trial fails.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from tivne.config import ObjectiveConfig

# objective.metric -> the metrics.json key it reads
METRIC_KEYS = {"ate": "ate_rmse_m", "chamfer": "object_chamfer_mean_m", "s_per_frame": "s_per_frame"}
# metrics.json key -> the keys that say why it is null
REASON_KEYS = {"ate_rmse_m": ("ate_reason",), "object_chamfer_mean_m": ("object_chamfer_reason", "mesh_eval_reason")}


def metric_value(metrics: Mapping[str, Any], key: str) -> tuple[float | None, str | None]:
    """(finite value, None) or (None, why it is missing) for one metrics.json key."""
    value = metrics.get(key)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value), None
    reason = next((metrics[k] for k in REASON_KEYS.get(key, ()) if metrics.get(k)), None)
    if reason is None and key not in metrics:
        reason = "not in metrics.json" + (" (the mesh metrics need output.evaluate=true)" if key == "object_chamfer_mean_m" else "")
    return None, f"{key} is {value!r}: {reason or 'not computable'}"


def objective_value(metrics: Mapping[str, Any], objective: ObjectiveConfig) -> tuple[float | None, str | None]:
    """The value to minimise and None, or None and the reason it is not computable.

    ``weighted``: Σ weight·metric over the terms with a weight > 0 (:class:`ObjectiveConfig`).
    """
    if objective.metric != "weighted":
        return metric_value(metrics, METRIC_KEYS[objective.metric])
    weights = {"ate": objective.ate_weight, "chamfer": objective.chamfer_weight, "s_per_frame": objective.time_weight}
    total = 0.0
    for name, weight in weights.items():
        if weight == 0:
            continue
        value, reason = metric_value(metrics, METRIC_KEYS[name])
        if value is None:
            return None, reason
        total += weight * value
    return total, None
