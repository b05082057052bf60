"""Keyframe database, reprojection overlap and window-selection policies (tivne/keyframes.py)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from tivne.config import KeyframeConfig
from tivne.render.rays import View
from tivne.slam.keyframes import KeyframePolicy, KeyframeStore, overlap_ratios

W, H = 80, 60
K = torch.tensor([[60.0, 0.0, 39.5], [0.0, 60.0, 29.5], [0.0, 0.0, 1.0]])
PLANE = 2.0  # fronto-parallel plane at z = 2 in the first camera's frame
FOOTPRINT = (W - 1) / 60.0 * PLANE  # width of the plane seen across the pixel centres


def shifted(dx: float) -> torch.Tensor:
    T = torch.eye(4)
    T[0, 3] = dx
    return T


def rot_y(angle: float) -> torch.Tensor:
    T = torch.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    T[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return T


def all_pixels() -> tuple[torch.Tensor, torch.Tensor]:
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    uv = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    return uv, torch.full((uv.shape[0],), PLANE)


def view(frame_id: int, pose: torch.Tensor) -> View:
    return View(frame_id, 0.0, torch.zeros(H, W, 3), torch.full((H, W), PLANE), None, pose)


def test_overlap_ratios_on_known_geometry():
    uv, depth = all_pixels()
    kf = torch.stack([torch.eye(4), rot_y(math.pi), shifted(FOOTPRINT / 2), shifted(-FOOTPRINT / 4), shifted(2 * FOOTPRINT)])
    r = overlap_ratios(uv, depth, K, torch.eye(4), kf, W, H)
    assert r.shape == (5,)
    assert float(r[0]) == 1.0
    assert float(r[1]) == 0.0  # looking the other way: every point behind the keyframe
    assert float(r[2]) == pytest.approx(0.5, abs=0.03)
    assert float(r[3]) == pytest.approx(0.75, abs=0.03)
    assert float(r[4]) == 0.0


def test_overlap_ratios_use_the_current_pose():
    uv, depth = all_pixels()
    cur = shifted(0.7)
    r = overlap_ratios(uv, depth, K, cur, torch.stack([cur, shifted(0.7 + FOOTPRINT / 2)]), W, H)
    assert float(r[0]) == 1.0 and float(r[1]) == pytest.approx(0.5, abs=0.03)


def test_database_insertion_every_n():
    db = KeyframeStore(KeyframeConfig(every=3))
    inserted = [k for k in range(10) if db.should_insert(k)]
    assert inserted == [0, 3, 6, 9]
    for k in inserted:
        assert db.add(view(k, shifted(0.1 * k))) == []  # nothing dropped: no limit
    assert len(db) == 4 and db.frame_ids() == [0, 3, 6, 9]
    assert db.poses().shape == (4, 4, 4) and float(db.poses()[2, 0, 3]) == pytest.approx(0.6)
    assert KeyframeStore(KeyframeConfig(every=1)).should_insert(7)
    with pytest.raises(ValueError, match="every"):
        KeyframeConfig(every=0)


def test_store_is_bounded_by_thinning_and_keeps_first_and_last():
    db = KeyframeStore(KeyframeConfig(every=1, max_stored=5))
    dropped = []
    for k in range(12):
        v = view(k, shifted(0.1 * k))
        v = dataclasses.replace(v, rgb=torch.full_like(v.rgb, 0.5))
        dropped += db.add(v)
        assert len(db) <= 5 and db.records[-1].frame_id == k and db.records[0].frame_id == 0
        assert db.records[-1].rgb.dtype == torch.uint8 and int(db.records[-1].rgb[0, 0, 0]) == 128
        assert v.rgb.dtype == torch.float32  # the view handed in is not changed
    kept = db.frame_ids()
    assert sorted(kept + [fid for fid, _ in dropped]) == list(range(12))  # every keyframe is kept or handed back
    assert all(float(pose[0, 3]) == pytest.approx(0.1 * fid) for fid, pose in dropped)  # with its final pose
    assert kept == sorted(kept) and max(b - a for a, b in zip(kept, kept[1:])) <= 4  # still spread over the sequence


def overlap_db() -> KeyframeStore:
    """Keyframes whose overlap with an identity-pose current frame is 1, 0.75, 0.5, 0.25, 0."""
    db = KeyframeStore(KeyframeConfig(every=1))
    for i, frac in enumerate([0.0, 0.25, 0.5, 0.75, 2.0]):
        db.add(view(i, shifted(frac * FOOTPRINT)))
    return db


def test_overlap_policy_picks_lowest_overlapping_keyframes():
    db = overlap_db()
    cur = view(10, torch.eye(4))
    policy = KeyframePolicy(KeyframeConfig("overlap", window=2, overlap_pixels=4000))
    picked = policy.select(db, cur, K, torch.Generator().manual_seed(0))
    assert picked == [2, 3]  # 0.5 and 0.25; keyframe 4 does not overlap at all
    wide = KeyframePolicy(KeyframeConfig("overlap", window=4, overlap_pixels=4000))
    assert wide.select(db, cur, K, torch.Generator().manual_seed(0)) == [0, 1, 2, 3]
    strict = KeyframePolicy(KeyframeConfig("overlap", window=2, overlap_pixels=4000, min_overlap=0.4))
    assert strict.select(db, cur, K, torch.Generator().manual_seed(0)) == [1, 2]  # 0.75, 0.5


def test_overlap_policy_falls_back_to_latest_when_nothing_overlaps():
    db = KeyframeStore(KeyframeConfig(every=1))
    for i in range(4):
        db.add(view(i, shifted(5.0 + i)))
    picked = KeyframePolicy(KeyframeConfig("overlap", window=2)).select(db, view(9, torch.eye(4)), K, torch.Generator().manual_seed(0))
    assert picked == [2, 3]


def test_policy_excludes_current_frame_and_returns_all_when_few():
    db = overlap_db()
    cur = view(3, shifted(0.75 * FOOTPRINT))  # keyframe 3 *is* the current frame
    picked = KeyframePolicy(KeyframeConfig("overlap", window=10)).select(db, cur, K)
    assert picked == [0, 1, 2, 4]
    picked = KeyframePolicy(KeyframeConfig("random", window=2)).select(db, cur, K, torch.Generator().manual_seed(0))
    assert 3 not in picked


@pytest.mark.parametrize("seed", range(5))
def test_random_policy_picks_k_distinct(seed):
    db = KeyframeStore(KeyframeConfig(every=1))
    for i in range(12):
        db.add(view(i, shifted(0.01 * i)))
    policy = KeyframePolicy(KeyframeConfig("random", window=4))
    picked = policy.select(db, view(99, torch.eye(4)), K, torch.Generator().manual_seed(seed))
    assert len(picked) == 4 and len(set(picked)) == 4 and picked == sorted(picked)
    assert all(0 <= i < 12 for i in picked)
    again = policy.select(db, view(99, torch.eye(4)), K, torch.Generator().manual_seed(seed))
    assert picked == again


def test_random_policy_covers_keyframes():
    db = KeyframeStore(KeyframeConfig(every=1))
    for i in range(8):
        db.add(view(i, torch.eye(4)))
    gen = torch.Generator().manual_seed(0)
    seen = set()
    for _ in range(30):
        seen |= set(KeyframePolicy(KeyframeConfig("random", window=2)).select(db, view(99, torch.eye(4)), K, gen))
    assert seen == set(range(8))


def test_policy_rejects_unknown_name():
    with pytest.raises(ValueError, match="policy"):
        KeyframePolicy(KeyframeConfig("nearest"))
