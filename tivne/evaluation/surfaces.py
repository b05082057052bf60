"""4D mesh metrics: a mesh of the scene at time t against the exact geometry at t, per moving object.

Everything here is in the dataset's world frame (the caller maps the SLAM-frame mesh there). With
``s`` the :class:`tivne.config.MeshEvalSettings` and ``[lo, hi]`` the span of the frames the run
processed, at mesh time t:

* per moving object ``<o>`` (:func:`object_metrics`):
    - ``<o>_accuracy_m``: mean distance from the mesh near the object (samples on the faces inside
      its GT box at t dilated by ``s.object_margin_m``) to the true surface at t (exact SDF). The
      whole surface, not the object's alone: static surface inside the dilated box (the floor under
      a box) is right where it is reconstructed and must not count as an error of the object.
    - ``<o>_completion_m`` / ``<o>_completion_ratio``: mean distance from, and share within
      ``s.threshold_m`` of, the object's true surface at t *that a camera saw* within
      ``[max(lo, t - s.window_s), min(hi, t + s.window_s)]`` to the mesh; faces nobody saw around
      t are not held against the reconstruction. ``<o>_chamfer_m``: mean of accuracy and completion.
    - ``<o>_completion_ratio_whole``: the ratio over the object's whole surface, and
      ``<o>_observed_ratio``: the share of it seen in that window (context for the two above).
* ``ghost_fraction``: share of samples on the whole mesh farther than ``s.threshold_m`` from the
  true surface at t (a moving object left where it was, floaters).
* static: ``static_accuracy_m`` (mesh outside the dilated object boxes to the static surface),
  ``static_completion_m`` / ``static_completion_ratio`` over the static surface seen by a camera in
  ``[lo, hi]``, ``static_chamfer_m``.

Values that cannot be computed are None and come with a ``<o>_reason`` / ``static_reason`` /
``reason`` string.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import trimesh

from tivne.config import MeshEvalSettings
from tivne.evaluation.ground_truth import GroundTruth, object_box, observed, surface_distance, surface_samples
from tivne.metrics.surface import (
    OrientedBox,
    accuracy,
    chamfer,
    completion,
    distance_to_points,
    faces_near,
    ghost_fraction,
    in_boxes,
    sample_mesh_surface,
)

OBJECT_VALUES = ("accuracy_m", "completion_m", "completion_ratio", "chamfer_m")
OBJECT_CONTEXT = ("completion_ratio_whole", "observed_ratio")
SCENE_VALUES = ("ghost_fraction", "static_accuracy_m", "static_completion_m", "static_completion_ratio", "static_chamfer_m")


def finite_or_none(value: float) -> float | None:
    """A metric value, or None where it is NaN / inf (not computable)."""
    return float(value) if math.isfinite(value) else None


def object_metrics(
    gt: GroundTruth,
    t: float,
    name: str,
    mesh: trimesh.Trimesh,
    mesh_samples: np.ndarray,
    span: tuple[float, float],
    settings: MeshEvalSettings,
) -> dict[str, Any]:
    """Accuracy, completion and Chamfer of moving object ``name`` at time ``t``.

    Args:
        mesh: the reconstruction at t, world frame; mesh_samples: (N, 3) samples on all of it.
        span: (lo, hi) seconds, the processed frames' time span.
    Returns:
        ``{name}_{value}`` for :data:`OBJECT_VALUES` and :data:`OBJECT_CONTEXT` (None where not
        computable) and ``{name}_reason`` when something is None.
    """
    s = settings
    box = object_box(gt, t, name)
    # The mesh near the object is sampled on its own, so its density does not depend on the scene size.
    near = sample_mesh_surface(faces_near(mesh, [box], s.object_margin_m), s.object_samples, seed=s.seed + 1)
    near = near[in_boxes(near, [box], s.object_margin_m)]
    truth = surface_samples(gt, t, s.object_samples, "dynamic", s.seed + 2, name)
    seen = observed(gt, truth, t, max(span[0], t - s.window_s), min(span[1], t + s.window_s), name)
    to_mesh = distance_to_points(np.concatenate([mesh_samples, near]))
    acc = accuracy(near, surface_distance(gt, t, "all"))
    comp, ratio = completion(truth[seen], to_mesh, s.threshold_m)
    values = {
        "accuracy_m": acc,
        "completion_m": comp,
        "completion_ratio": ratio,
        "chamfer_m": chamfer(acc, comp),
        "completion_ratio_whole": completion(truth, to_mesh, s.threshold_m)[1],
        "observed_ratio": float(seen.mean()) if len(seen) else math.nan,
    }
    out: dict[str, Any] = {f"{name}_{k}": finite_or_none(v) for k, v in values.items()}
    reasons = []
    if len(truth) == 0:
        reasons.append("the dataset has no surface for this object")
    elif not seen.any():
        reasons.append(f"no camera saw it within {s.window_s} s of t")
    if len(near) == 0:
        reasons.append(f"no reconstructed surface within {s.object_margin_m} m of its box")
    if reasons:
        out[f"{name}_reason"] = "; ".join(reasons)
    return out


def static_metrics(
    gt: GroundTruth,
    t: float,
    mesh_samples: np.ndarray,
    boxes: Sequence[OrientedBox],
    span: tuple[float, float],
    settings: MeshEvalSettings,
) -> dict[str, Any]:
    """Accuracy and completion of the static scene at time ``t`` (see the module docstring).

    Args:
        mesh_samples: (N, 3) samples on the whole mesh at t, world frame.
        boxes: the moving objects' boxes at t (their dilated insides are left out of the accuracy).
        span: (lo, hi) seconds; static surface seen by any camera in it counts for completion.
    """
    s = settings
    outside = mesh_samples[~in_boxes(mesh_samples, boxes, s.object_margin_m)]
    truth = surface_samples(gt, t, s.static_samples, "static", s.seed + 3)
    seen = observed(gt, truth, t, span[0], span[1])
    acc = accuracy(outside, surface_distance(gt, t, "static"))
    comp, ratio = completion(truth[seen], mesh_samples, s.threshold_m)
    out: dict[str, Any] = {
        "static_accuracy_m": finite_or_none(acc),
        "static_completion_m": finite_or_none(comp),
        "static_completion_ratio": finite_or_none(ratio),
        "static_chamfer_m": finite_or_none(chamfer(acc, comp)),
    }
    if not seen.any():
        out["static_reason"] = "no static surface seen by the processed frames"
    elif len(outside) == 0:
        out["static_reason"] = "no reconstructed surface outside the moving objects' boxes"
    return out


def mesh_time_metrics(
    gt: GroundTruth, t: float, mesh: trimesh.Trimesh, span: tuple[float, float], settings: MeshEvalSettings = MeshEvalSettings()
) -> dict[str, Any]:
    """Every mesh metric at one time ``t`` (keys without the ``mesh_t..._`` prefix).

    Args:
        mesh: the reconstruction at t in the dataset's world frame.
        span: (lo, hi) seconds, the time span of the processed frames.
    Returns:
        :data:`SCENE_VALUES` and, per object ``o``, ``o_<value>`` for :data:`OBJECT_VALUES` and
        :data:`OBJECT_CONTEXT`, with ``*_reason`` keys where values are None (``reason`` for an
        empty mesh).
    """
    s = settings
    samples = sample_mesh_surface(mesh, s.pred_samples, seed=s.seed)
    if len(samples) == 0:
        out: dict[str, Any] = {k: None for k in SCENE_VALUES}
        out.update({f"{o}_{k}": None for o in gt.object_names for k in OBJECT_VALUES + OBJECT_CONTEXT})
        return {**out, "reason": "empty mesh"}
    out = {"ghost_fraction": finite_or_none(ghost_fraction(samples, surface_distance(gt, t, "all"), s.threshold_m))}
    for name in gt.object_names:
        out.update(object_metrics(gt, t, name, mesh, samples, span, s))
    boxes = [object_box(gt, t, name) for name in gt.object_names]
    out.update(static_metrics(gt, t, samples, boxes, span, s))
    return out


# --------------------------------------------------------------------------------------------------
# Flat keys
# --------------------------------------------------------------------------------------------------


def time_label(t: float) -> str:
    """Key prefix of a mesh time: ``mesh_t{t:.2f}``."""
    return f"mesh_t{t:.2f}"


def with_label(name: str, label: str) -> str:
    """``cube_accuracy_m`` + ``first`` -> ``cube_accuracy_first_m`` (the unit suffix stays last)."""
    return f"{name[:-2]}_{label}_m" if name.endswith("_m") else f"{name}_{label}"


def flatten_mesh_metrics(
    per_time: Mapping[float, Mapping[str, Any]], objects: Sequence[str], first: float | None = None, last: float | None = None
) -> dict[str, Any]:
    """Per-time values -> flat metrics.json keys.

    Args:
        per_time: {t: :func:`mesh_time_metrics` output}.
        objects: the moving objects' names.
        first, last: the processed frames' first / last time when it is one of ``per_time``'s keys.
    Returns:
        ``mesh_t{t:.2f}_<name>`` for every value; ``<name>_first`` / ``<name>_last`` (unit last:
        ``cube_accuracy_first_m``, null with ``cube_accuracy_first_reason``) for the scene values
        and the objects' :data:`OBJECT_VALUES`;
        ``object_chamfer_mean_m`` / ``object_chamfer_max_m`` over every object and time, and
        ``ghost_fraction_max`` over the times (null with a ``*_reason`` when nothing was computable).
    """
    out: dict[str, Any] = {}
    for t, values in per_time.items():
        out.update({f"{time_label(t)}_{k}": v for k, v in values.items()})
    # Each summarised value with the key of the reason it may be null for.
    summarised = {"ghost_fraction": "reason", **{k: "static_reason" for k in SCENE_VALUES[1:]}}
    summarised.update({f"{o}_{k}": f"{o}_reason" for o in objects for k in OBJECT_VALUES})
    for label, t in (("first", first), ("last", last)):
        if t is None or t not in per_time:
            continue
        for name, why in summarised.items():
            key = with_label(name, label)
            out[key] = per_time[t].get(name)
            if out[key] is None:  # cube_accuracy_first_m -> cube_accuracy_first_reason
                out[key.removesuffix("_m") + "_reason"] = per_time[t].get(why) or per_time[t].get("reason") or "not computable"
    chamfers = {(o, t): v.get(f"{o}_chamfer_m") for t, v in per_time.items() for o in objects}
    known = [c for c in chamfers.values() if c is not None]
    out["object_chamfer_mean_m"] = float(np.mean(known)) if known else None
    out["object_chamfer_max_m"] = max(known) if known else None
    missing = [f"{o} at t={t:.2f}" for (o, t), c in chamfers.items() if c is None]
    if not chamfers:
        out["object_chamfer_reason"] = "no moving objects"
    elif missing:  # the summaries cover the others; say which are left out
        out["object_chamfer_reason"] = "not computable for " + ", ".join(missing)
    ghosts = [v["ghost_fraction"] for v in per_time.values() if v.get("ghost_fraction") is not None]
    out["ghost_fraction_max"] = max(ghosts) if ghosts else None
    if not ghosts:
        out["ghost_fraction_reason"] = "no non-empty mesh"
    return out

