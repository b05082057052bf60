"""SparseVoxelGrid and its pure helpers (tivne/field/voxels.py)."""

from __future__ import annotations

import pytest
import torch

from tivne.field.voxels import (
    CORNER_OFFSETS,
    GridCapacityError,
    SparseVoxelGrid,
    bracketing_observations,
    merge_order,
    pack_coords,
    sorted_lookup,
    trilinear_weights,
    unpack_keys,
)


def corner_row_table(grid: SparseVoxelGrid) -> dict[tuple[int, int, int], int]:
    """(corner lattice coords) -> embedding row, from the grid's own corner table."""
    return {tuple(c.tolist()): int(r) for c, r in zip(unpack_keys(grid.corner_keys), grid.corner_rows)}


def brute_force_lookup(grid: SparseVoxelGrid, points: torch.Tensor) -> torch.Tensor:
    """Reference trilinear interpolation written with Python loops (float64)."""
    rows = corner_row_table(grid)
    E = grid.embeddings.detach().double()
    out = []
    for p in points.double():
        g = p / grid.voxel_size
        base = [int(torch.floor(x)) for x in g]
        frac = [float(x) - b for x, b in zip(g, base)]
        acc = torch.zeros(grid.embed_dim, dtype=torch.float64)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    w = (frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1]) * (frac[2] if dz else 1 - frac[2])
                    acc += w * E[rows[(base[0] + dx, base[1] + dy, base[2] + dz)]]
        out.append(acc)
    return torch.stack(out)


# ---- pure helpers -------------------------------------------------------------------------------


def test_pack_unpack_roundtrip_and_order():
    coords = torch.tensor([[0, 0, 0], [-1, 2, -3], [5, -7, 11], [-(2**20), 2**20 - 1, 0]])
    torch.testing.assert_close(unpack_keys(pack_coords(coords)), coords)
    # x-major order: sorting keys sorts lexicographically by (x, y, z)
    a, b = pack_coords(torch.tensor([[0, 5, 5], [1, -5, -5]]))
    assert a < b
    with pytest.raises(ValueError, match="range"):
        pack_coords(torch.tensor([[2**20, 0, 0]]))


def test_sorted_lookup_found_and_missing():
    keys = torch.tensor([2, 5, 9])
    pos, found = sorted_lookup(keys, torch.tensor([5, 9, 2, 3, 100, -1]))
    assert found.tolist() == [True, True, True, False, False, False]
    assert pos[:3].tolist() == [1, 2, 0]
    assert (pos >= 0).all() and (pos <= 2).all()
    pos, found = sorted_lookup(torch.zeros(0, dtype=torch.long), torch.tensor([1, 2]))
    assert not found.any()


@pytest.mark.parametrize("n, m", [(0, 5), (5, 0), (1000, 37), (37, 1000)])
def test_merge_order_sorts_two_sorted_disjoint_key_sets(n, m):
    keys = torch.randperm(10 * (n + m) + 1, generator=torch.Generator().manual_seed(n))[: n + m] - 3 * (n + m)
    a, b = keys[:n].sort().values, keys[n:].sort().values
    merged = torch.cat([a, b])[merge_order(a, b)]
    assert torch.equal(merged, keys.sort().values)


def test_a_growing_map_keeps_its_keys_sorted_and_its_rows():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, surface_cell=0.02)
    g = torch.Generator().manual_seed(1)
    for _ in range(5):
        grid.allocate(torch.rand(300, 3, generator=g) * 2 - 1, dilation=1)
        for keys in (grid.voxel_keys, grid.corner_keys, grid.surface_keys):
            assert bool((keys[1:] > keys[:-1]).all())
    # every voxel's corner rows are the rows of its corners' keys
    corners = pack_coords(unpack_keys(grid.voxel_keys)[:, None, :] + CORNER_OFFSETS)
    pos, found = sorted_lookup(grid.corner_keys, corners)
    assert found.all() and torch.equal(grid.corner_rows[pos], grid.voxel_corner_rows)


def test_trilinear_weights_corners_and_partition_of_unity():
    # At a corner lattice point the weight is one-hot on that corner (order 4*dx + 2*dy + dz).
    w = trilinear_weights(CORNER_OFFSETS.double())
    torch.testing.assert_close(w, torch.eye(8, dtype=torch.float64))
    frac = torch.rand(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    w = trilinear_weights(frac)
    torch.testing.assert_close(w.sum(-1), torch.ones(50, dtype=torch.float64))
    assert (w >= 0).all()
    # Reproduces the position: sum_i w_i * corner_i == frac.
    torch.testing.assert_close(w @ CORNER_OFFSETS.double(), frac)


# ---- allocation ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lookup_matches_brute_force_reference(dtype):
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    # embeddings O(0.1) in float32 (its round-off on the fraction is ~1e-7 relative), O(1) in float64
    std = 0.1 if dtype == torch.float32 else 1.0
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=5, capacity=16, init_std=std).to(dtype)
    anchors = (torch.rand(20, 3, generator=gen, dtype=torch.float64) * 2 - 1).to(dtype)
    grid.allocate(anchors, dilation=1)
    # random points inside allocated voxels: jitter the anchors by < half a voxel
    points = anchors + ((torch.rand(20, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.09).to(dtype)
    points = torch.cat([points, anchors])
    feats, valid = grid.lookup(points)
    assert valid.all()
    torch.testing.assert_close(feats.double(), brute_force_lookup(grid, points), atol=1e-6, rtol=0)


def test_adjacent_voxels_share_four_corner_rows():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=32)
    assert grid.allocate(torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]])) == 2
    assert grid.num_corners == 12
    rows = grid.voxel_corner_rows  # sorted by key: voxel (0,0,0) then (1,0,0)
    assert unpack_keys(grid.voxel_keys).tolist() == [[0, 0, 0], [1, 0, 0]]
    shared = set(rows[0].tolist()) & set(rows[1].tolist())
    assert len(shared) == 4
    # the shared rows are exactly the dx=1 corners of voxel 0 and the dx=0 corners of voxel 1
    assert rows[0, 4:].tolist() == rows[1, :4].tolist()
    # and they are really shared: at the common face both voxels interpolate the same value
    face = torch.tensor([[0.1 - 1e-7, 0.03, 0.07], [0.1 + 1e-7, 0.03, 0.07]])
    feats, valid = grid.lookup(face)
    assert valid.all()
    torch.testing.assert_close(feats[0], feats[1], atol=1e-5, rtol=0)


def test_allocation_is_idempotent():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=64)
    pts = torch.tensor([[0.05, 0.05, 0.05], [0.33, -0.21, 0.9], [0.06, 0.07, 0.08]])
    assert grid.allocate(pts) == 2  # two points share a voxel
    state = {k: v.clone() for k, v in grid.state_dict().items()}
    assert grid.allocate(pts) == 0
    assert grid.allocate(pts, dilation=0) == 0
    for k, v in grid.state_dict().items():
        if k == "voxel_hits":  # counts the observations; the map itself is unchanged
            assert v.tolist() == [3, 3] and state[k].tolist() == [1, 1]
        else:
            torch.testing.assert_close(v, state[k])


def test_dilation_allocates_chebyshev_neighbourhood():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=8)
    assert grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]), dilation=1) == 27
    assert grid.num_voxels == 27 and grid.num_corners == 64
    coords = grid.voxel_coords()
    assert coords.min().item() == -1 and coords.max().item() == 1
    grid2 = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=8)
    assert grid2.allocate(torch.tensor([[0.05, 0.05, 0.05]]), dilation=2) == 125


def test_points_outside_allocated_voxels_are_invalid():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=3, capacity=16)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]))
    pts = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [-0.01, 0.05, 0.05], [5.0, 5.0, 5.0]])
    feats, valid = grid.lookup(pts)
    assert valid.tolist() == [True, False, False, False]
    assert feats.shape == (1, 3)
    assert grid.contains(pts).tolist() == [True, False, False, False]


def test_empty_grid_lookup_is_all_invalid():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=3, capacity=4)
    feats, valid = grid.lookup(torch.zeros(4, 3))
    assert feats.shape == (0, 3) and not valid.any()


def test_non_finite_and_huge_points_are_invalid_not_errors():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=3, capacity=16)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]))
    bad = torch.tensor(
        [[float("nan"), 0.05, 0.05], [float("inf"), 0.05, 0.05], [0.05, -float("inf"), 0.05], [1e9, 0.0, 0.0], [0.0, 0.0, -1e12]]
    )
    feats, valid = grid.lookup(torch.cat([bad, torch.tensor([[0.05, 0.05, 0.05]])]))
    assert valid.tolist() == [False] * 5 + [True]
    assert torch.isfinite(feats).all()
    # allocating from a diverged pose is ignored rather than raising
    n_before = grid.num_voxels
    assert grid.allocate(bad) == 0
    assert grid.num_voxels == n_before


# ---- growth and the hard cap -------------------------------------------------------------------


def test_growth_beyond_capacity_keeps_rows_values_and_parameter():
    torch.manual_seed(0)
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=3, capacity=8, max_capacity=10_000, init_std=1.0)
    param = grid.embeddings
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]))
    assert grid.capacity == 8
    probe = torch.tensor([[0.02, 0.07, 0.04]])
    before_feat, _ = grid.lookup(probe)
    before_rows = grid.embeddings.detach()[:8].clone()
    before_map = corner_row_table(grid)
    calls = []
    grid.grow_callbacks.append(lambda old, new: calls.append((old, new)))
    grid.allocate(torch.rand(30, 3) * 2)
    assert grid.capacity >= grid.num_corners > 8
    assert calls and calls[0][0] == 8 and calls[-1][1] == grid.capacity
    assert grid.embeddings is param  # optimisers keep the same Parameter
    torch.testing.assert_close(grid.embeddings.detach()[:8], before_rows)
    after_map = corner_row_table(grid)
    assert all(after_map[c] == r for c, r in before_map.items())
    after_feat, valid = grid.lookup(probe)
    assert valid.all()
    torch.testing.assert_close(after_feat, before_feat)
    # every row in use is a distinct, in-capacity row
    assert grid.corner_rows.unique().numel() == grid.num_corners
    assert int(grid.corner_rows.max()) < grid.capacity


def test_hard_cap_raises_clear_error():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=8, max_capacity=20)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]))  # 8 rows
    with pytest.raises(GridCapacityError, match=r"max_capacity is 20") as info:
        grid.allocate(torch.tensor([[5.05, 5.05, 5.05], [-5.05, -5.05, -5.05]]))  # +16 rows > 20
    assert "field.max_capacity" in str(info.value) and "24" in str(info.value)
    assert isinstance(info.value, RuntimeError)


def test_invalid_voxel_size_rejected():
    with pytest.raises(ValueError, match="voxel_size"):
        SparseVoxelGrid(voxel_size=0.0)


# ---- gradients ----------------------------------------------------------------------------------


def test_gradient_reaches_only_the_eight_touched_rows():
    torch.manual_seed(0)
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=4, capacity=64)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05], [0.45, 0.45, 0.45]]))
    p = torch.tensor([[0.03, 0.06, 0.02]])
    feats, _ = grid.lookup(p)
    feats.sum().backward()
    grad = grid.embeddings.grad
    touched = (grad.abs().sum(-1) > 0).nonzero()[:, 0]
    rows = corner_row_table(grid)
    expected = sorted(rows[tuple(o.tolist())] for o in CORNER_OFFSETS)
    assert touched.tolist() == expected
    # d(sum feats)/dE_row = trilinear weight of that corner, same for every channel
    w = trilinear_weights(torch.tensor([[0.3, 0.6, 0.2]]))[0]
    for i, o in enumerate(CORNER_OFFSETS):
        torch.testing.assert_close(grad[rows[tuple(o.tolist())]], w[i].expand(4), atol=1e-5, rtol=0)


def test_gradient_wrt_point_matches_finite_differences():
    torch.manual_seed(0)
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=3, capacity=16, init_std=1.0).double()
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]], dtype=torch.float64))
    proj = torch.randn(3, dtype=torch.float64)
    p = torch.tensor([[0.031, 0.062, 0.047]], dtype=torch.float64, requires_grad=True)

    def f(x):
        feats, valid = grid.lookup(x)
        assert valid.all()
        return (feats @ proj).sum()

    f(p).backward()
    eps = 1e-6
    fd = torch.zeros(3, dtype=torch.float64)
    with torch.no_grad():
        for i in range(3):
            d = torch.zeros_like(p)
            d[0, i] = eps
            fd[i] = (f(p + d) - f(p - d)) / (2 * eps)
    assert fd.abs().max() > 1e-3  # a real, non-zero spatial gradient
    torch.testing.assert_close(p.grad[0], fd, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradcheck(f, (p,))


def test_contains_non_finite_and_huge_points_is_false():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=3, capacity=16)
    grid.allocate(torch.tensor([[0.05, 0.05, 0.05]]))
    pts = torch.tensor([[0.05, 0.05, 0.05], [float("nan"), 0.0, 0.0], [1e9, 0.0, 0.0]])
    assert grid.contains(pts).tolist() == [True, False, False]


def test_hits_count_observed_voxels_not_the_dilation_shell():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=8)
    point = torch.tensor([[0.05, 0.05, 0.05]])
    grid.allocate(point, dilation=1)
    grid.allocate(torch.cat([point, torch.tensor([[0.15, 0.05, 0.05]])]), dilation=1)  # a neighbour is hit once
    hits = {tuple(c.tolist()): int(h) for c, h in zip(grid.voxel_coords(), grid.voxel_hits)}
    assert len(hits) == 27 + 9 and hits[(0, 0, 0)] == 2 and hits[(1, 0, 0)] == 1
    assert sum(h > 0 for h in hits.values()) == 2
    probe = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05], [-0.05, 0.05, 0.05], [5.0, 0.0, 0.0]])
    assert grid.contains(probe).tolist() == [True, True, True, False]
    assert grid.contains(probe, min_hits=1).tolist() == [True, True, False, False]
    assert grid.contains(probe, min_hits=2).tolist() == [True, False, False, False]
    assert not SparseVoxelGrid(voxel_size=0.1, embed_dim=2).contains(probe, min_hits=1).any()


def test_hits_survive_a_checkpoint_and_old_checkpoints_count_as_observed(tmp_path):
    from tivne.field.clock import Clock
    from tivne.field.networks import TimeVaryingField
    from tivne.slam.checkpoint import load_checkpoint, save_checkpoint

    kwargs = dict(time=False, voxel_size=0.1, embed_dim=4, capacity=8, hidden_dim=8, num_hidden=3, time_frequencies=1)
    field = TimeVaryingField(**kwargs)
    field.grid.allocate(torch.tensor([[0.05, 0.05, 0.05], [0.95, 0.05, 0.05]]), dilation=1)
    path = save_checkpoint(tmp_path / "a.pt", field, [0.0], torch.eye(4)[None], Clock(0.0))
    back, _ = load_checkpoint(path)
    assert torch.equal(back.grid.voxel_hits, field.grid.voxel_hits) and int((back.grid.voxel_hits > 0).sum()) == 2
    payload = torch.load(path, weights_only=True)
    del payload["field_state"]["grid.voxel_hits"]
    torch.save(payload, tmp_path / "old.pt")
    old, _ = load_checkpoint(tmp_path / "old.pt")
    assert (old.grid.voxel_hits == 1).all() and old.grid.num_voxels == field.grid.num_voxels


def test_dynamic_points_record_voxel_and_time_instead_of_hits():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=8)
    pts = torch.tensor([[0.05, 0.05, 0.05], [1.05, 0.05, 0.05]])
    grid.allocate(pts, dynamic=torch.tensor([False, True]), tau=0.5)
    grid.allocate(torch.tensor([[2.05, 0.05, 0.05]]), dynamic=torch.tensor([True]), tau=2.0)
    assert grid.num_voxels == 3 and int((grid.voxel_hits > 0).sum()) == 1
    assert unpack_keys(grid.dynamic_keys).tolist() == [[10, 0, 0], [20, 0, 0]] and grid.dynamic_tau.tolist() == [0.5, 2.0]
    probe = torch.tensor([[0.05, 0.05, 0.05], [1.05, 0.05, 0.05], [2.05, 0.05, 0.05]])
    assert grid.observed(probe).tolist() == [True, False, False]  # no time: static hits only
    assert grid.observed(probe, tau=0.6, window=0.2).tolist() == [True, True, False]
    assert grid.observed(probe, tau=1.9, window=0.2).tolist() == [True, False, True]
    assert grid.observed(probe, tau=1.0, window=0.2).tolist() == [True, False, False]


def test_bracketing_observations_keep_the_nearest_time_on_each_side_within_the_window():
    times = torch.tensor([0.5, 0.6, 0.6, 0.7, 0.9, 2.0])
    assert bracketing_observations(times, 0.62, 0.2).tolist() == [False, True, True, True, False, False]
    assert bracketing_observations(times, 0.6, 0.2).tolist() == [False, True, True, False, False, False]
    assert bracketing_observations(times, 1.5, 0.2).tolist() == [False] * 6  # none within the window
    assert bracketing_observations(times, 1.85, 0.2).tolist() == [False] * 5 + [True]  # only after
    assert bracketing_observations(times, 3.0, 10.0).tolist() == [False] * 5 + [True]  # only before


def test_a_moving_object_shows_where_it_was_seen_around_tau_not_along_its_path():
    grid = SparseVoxelGrid(voxel_size=0.1, embed_dim=2, capacity=16)
    for i, tau in enumerate((0.0, 0.1, 0.2, 0.3)):  # one voxel further along x at each observation
        grid.allocate(torch.tensor([[0.05 + 0.1 * i, 0.05, 0.05]]), dynamic=torch.tensor([True]), tau=tau)
    probe = torch.tensor([[0.05 + 0.1 * i, 0.05, 0.05] for i in range(4)])
    assert grid.observed(probe, min_hits=1, tau=0.15, window=0.2).tolist() == [False, True, True, False]
    assert grid.observed(probe, min_hits=1, tau=0.3, window=0.2).tolist() == [False, False, False, True]


def test_surface_record_holds_static_depth_cells_and_survives_a_checkpoint(tmp_path):
    from tivne.field.clock import Clock
    from tivne.field.networks import TimeVaryingField
    from tivne.slam.checkpoint import load_checkpoint, save_checkpoint

    kwargs = dict(time=False, voxel_size=0.1, embed_dim=4, capacity=8, hidden_dim=8, num_hidden=3, time_frequencies=1, surface_cell=0.02)
    field = TimeVaryingField(**kwargs)
    grid = field.grid
    assert grid.near_surface(torch.tensor([[5.0, 5.0, 5.0]])).all()  # nothing recorded: no opinion
    grid.allocate(torch.tensor([[0.01, 0.01, 0.01], [0.51, 0.01, 0.01]]), dynamic=torch.tensor([False, True]), tau=0.3)
    grid.allocate(torch.tensor([[0.015, 0.01, 0.01]]))  # same cell again: no duplicate key
    assert unpack_keys(grid.surface_keys).tolist() == [[0, 0, 0]]
    probe = torch.tensor([[0.01, 0.01, 0.01], [0.03, -0.01, 0.03], [0.07, 0.01, 0.01], [0.51, 0.01, 0.01]])
    assert grid.near_surface(probe).tolist() == [True, True, False, False]  # one cell around; not the moving point
    back, _ = load_checkpoint(save_checkpoint(tmp_path / "a.pt", field, [0.0], torch.eye(4)[None], Clock(0.0)))
    assert torch.equal(back.grid.surface_keys, grid.surface_keys) and back.grid.surface_cell == 0.02
