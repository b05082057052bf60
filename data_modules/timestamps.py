"""Timestamp checks and the one timestamp association (TUM ``associate.py``) every module uses."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from data_modules.frame import DatasetError


def check_monotonic_timestamps(timestamps: Sequence[float] | np.ndarray, source: str) -> np.ndarray:
    """Return ``timestamps`` (N,) as float64; raise :class:`DatasetError` unless strictly increasing and finite."""
    ts = np.asarray(timestamps, dtype=np.float64)
    if ts.ndim != 1:
        raise DatasetError(source, f"timestamps must be 1-D, got shape {ts.shape}")
    if not np.isfinite(ts).all():
        bad = int(np.flatnonzero(~np.isfinite(ts))[0])
        raise DatasetError(source, f"timestamp {bad} is not finite")
    if ts.size > 1:
        step = np.diff(ts)
        if (step <= 0).any():
            bad = int(np.flatnonzero(step <= 0)[0]) + 1
            raise DatasetError(source, f"timestamps are not strictly increasing at entry {bad} ({ts[bad - 1]:.6f} -> {ts[bad]:.6f})")
    return ts


def _as_float64(x: Sequence[float] | np.ndarray | torch.Tensor) -> np.ndarray:
    """Any 1-D sequence, array or tensor (any device) -> flat numpy float64."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64).reshape(-1)


def associate_by_timestamp(
    first: Sequence[float] | np.ndarray | torch.Tensor,
    second: Sequence[float] | np.ndarray | torch.Tensor,
    max_diff: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp association, as TUM's ``associate.py``.

    Boundary convention: ``|first[i] - second[j]| <= max_diff`` (inclusive, compared in float64 as
    computed) makes (i, j) a candidate. Candidates are accepted greedily by increasing difference,
    each index at most once; ties go to the lower ``i``, then the lower ``j`` (deterministic).

    Args:
        first: (N,) seconds, any order (e.g. colour stamps, or an estimated trajectory's).
        second: (M,) seconds, any order (e.g. depth stamps, or the reference trajectory's).
        max_diff: largest accepted time difference in seconds (inclusive).
    Returns:
        idx_first (K,) and idx_second (K,) int64 indices of the matched pairs, sorted by ``idx_first``.
    """
    a, b = _as_float64(first), _as_float64(second)
    empty = np.zeros(0, dtype=np.int64)
    if len(a) == 0 or len(b) == 0:
        return empty, empty.copy()
    order = np.argsort(b, kind="stable")
    b_sorted = b[order]
    # Candidate window of every element of `a` in the sorted `b`: [lo, hi), widened by a few ulps so
    # that rounding in a +- max_diff never drops a pair; the exact test below decides.
    slack = 4 * np.spacing(np.abs(a) + max_diff)
    lo = np.searchsorted(b_sorted, a - max_diff - slack, side="left")
    hi = np.searchsorted(b_sorted, a + max_diff + slack, side="right")
    counts = hi - lo
    cand_a = np.repeat(np.arange(len(a)), counts)
    # Position inside each window: running index minus the window's start in the flattened list.
    starts = np.repeat(np.cumsum(counts) - counts, counts)
    cand_b = order[np.repeat(lo, counts) + (np.arange(counts.sum()) - starts)]
    diff = np.abs(a[cand_a] - b[cand_b])
    keep = diff <= max_diff
    cand_a, cand_b, diff = cand_a[keep], cand_b[keep], diff[keep]
    used_a = np.zeros(len(a), dtype=bool)
    used_b = np.zeros(len(b), dtype=bool)
    pairs = []
    for k in np.lexsort((cand_b, cand_a, diff)):
        i, j = cand_a[k], cand_b[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            pairs.append((i, j))
    if not pairs:
        return empty, empty.copy()
    idx = np.array(sorted(pairs), dtype=np.int64)
    return idx[:, 0], idx[:, 1]
