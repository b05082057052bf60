"""data_modules.timestamps: monotonic checks and the one timestamp association."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from data_modules.frame import DatasetError
from data_modules.timestamps import associate_by_timestamp, check_monotonic_timestamps

F64 = torch.float64


def pairs(first, second, max_diff) -> list[tuple[int, int]]:
    """The association as a list of (i, j) pairs."""
    i, j = associate_by_timestamp(first, second, max_diff)
    return list(zip(i.tolist(), j.tolist()))


def test_check_monotonic_timestamps():
    assert check_monotonic_timestamps([0.0, 0.1, 0.3], "t").dtype == np.float64
    with pytest.raises(DatasetError, match="not strictly increasing at entry 2"):
        check_monotonic_timestamps([0.0, 0.1, 0.1], "assoc.txt")
    with pytest.raises(DatasetError, match="not strictly increasing"):
        check_monotonic_timestamps([0.0, 0.2, 0.1], "assoc.txt")
    with pytest.raises(DatasetError, match="not finite"):
        check_monotonic_timestamps([0.0, float("nan")], "assoc.txt")
    with pytest.raises(DatasetError, match="1-D"):
        check_monotonic_timestamps([[0.0, 1.0]], "assoc.txt")


class TestAssociateByTimestamp:
    def test_exact_and_jittered(self):
        ref = np.arange(10) * 0.033
        est = ref[::2] + 0.004
        i_est, i_ref = associate_by_timestamp(est, ref, max_diff=0.01)
        assert i_est.tolist() == list(range(5)) and i_ref.tolist() == [0, 2, 4, 6, 8]
        assert i_est.dtype == np.int64

    def test_one_to_one_greedy(self):
        # Both estimates are closest to ref[1]; the closer one (est 1) wins it, est 0 gets ref[0].
        ref = np.array([0.0, 1.0])
        est = np.array([0.985, 0.999])
        i_est, i_ref = associate_by_timestamp(est, ref, max_diff=0.02)
        assert list(zip(i_est.tolist(), i_ref.tolist())) == [(1, 1)]
        i_est, i_ref = associate_by_timestamp(est, ref, max_diff=2.0)
        assert list(zip(i_est.tolist(), i_ref.tolist())) == [(0, 0), (1, 1)]

    def test_outside_tolerance_and_empty(self):
        i_est, i_ref = associate_by_timestamp([0.0, 10.0], [0.5, 10.001], max_diff=0.02)
        assert i_est.tolist() == [1] and i_ref.tolist() == [1]
        e1, e2 = associate_by_timestamp([], [1.0])
        assert len(e1) == len(e2) == 0
        e1, e2 = associate_by_timestamp([5.0], [1.0])
        assert len(e1) == len(e2) == 0

    def test_unsorted_inputs_and_torch(self):
        ref = torch.tensor([0.3, 0.1, 0.2], dtype=F64)
        est = np.array([0.201, 0.101, 0.301])
        i_est, i_ref = associate_by_timestamp(est, ref)
        assert i_est.tolist() == [0, 1, 2] and i_ref.tolist() == [2, 1, 0]

    def test_matches_brute_force_greedy(self):
        rng = np.random.default_rng(0)
        est = np.sort(rng.uniform(0, 3, 80))
        ref = np.sort(rng.uniform(0, 3, 100))
        cands = sorted((abs(a - b), i, j) for i, a in enumerate(est) for j, b in enumerate(ref) if abs(a - b) <= 0.02)
        used_i, used_j, pairs = set(), set(), []
        for _, i, j in cands:
            if i not in used_i and j not in used_j:
                used_i.add(i), used_j.add(j), pairs.append((i, j))
        i_est, i_ref = associate_by_timestamp(est, ref, 0.02)
        assert list(zip(i_est.tolist(), i_ref.tolist())) == sorted(pairs)

    def test_boundary_is_inclusive(self):
        # |dt| == max_diff is a match (binary fractions: the differences are exact in float64)
        assert pairs([0.5, 2.0], [0.75, 2.25 + 2**-20], 0.25) == [(0, 0)]
        assert pairs([1.0], [0.75], 0.25) == [(0, 0)]
        assert pairs([1.0], [0.75 - 2**-30], 0.25) == []


def test_associate_is_greedy_and_unique():
    a = np.array([0.0, 0.01, 0.1])
    b = np.array([0.008, 0.5])
    assert pairs(a, b, 0.02) == [(1, 0)]  # 0.01 is closer to 0.008 than 0.0 is
    assert pairs([0.0, 1.0], [0.015, 0.99], 0.02) == [(0, 0), (1, 1)]
