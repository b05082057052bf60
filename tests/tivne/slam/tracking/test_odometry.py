"""Dense RGB-D odometry (tivne/slam/odometry.py): known motions, robust weights, pyramid, failure signals."""

from __future__ import annotations

import math

import pytest
import torch

from data_modules.synthetic import SyntheticSequence
from tivne.geometry import backproject, invert_pose, se3_exp, se3_step
from tivne.slam.tracking.odometry import (
    OdometryConfig,
    PosePrior,
    frame_pyramid,
    parallax_pixels,
    rgbd_odometry,
    track_pyramids,
)
from tivne.slam.tracking.pyramid import (
    build_pyramid,
    crop_pyramid,
    downsample_depth,
    downsample_K,
    downsample_mask,
    image_gradients,
    vertex_normals,
)
from tivne.slam.tracking.robust import cauchy_weights, huber_weights, normal_equations, robust_scale

W, H = 160, 120


@pytest.fixture(scope="module")
def room() -> SyntheticSequence:
    """The procedural room of the cube scene, exact depth and noise-free (8-bit) colour."""
    return SyntheticSequence("cube", num_frames=2, width=W, height=H, depth_noise=False, rgb_noise=0.0, cache_dir=None)


def view(seq: SyntheticSequence, c2w: torch.Tensor, t: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """rgb (H, W, 3) quantised to 8 bits, depth (H, W) float32, cube mask (H, W) of the room seen from c2w at time t."""
    rgb, depth, labels = seq.render_at(c2w, t)
    return rgb, depth, labels > 0


def motion(seed: int, trans_m: float, rot_deg: float) -> torch.Tensor:
    """(4, 4) float64 rigid motion with a random axis and direction of the given sizes."""
    xi = torch.randn(6, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return se3_exp(torch.cat([xi[:3] / xi[:3].norm() * trans_m, xi[3:] / xi[3:].norm() * math.radians(rot_deg)]))


def pose_error(T: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """(translation error mm, rotation error deg) of T against truth."""
    E = invert_pose(truth) @ T.to(truth.dtype)
    return float(E[:3, 3].norm()) * 1e3, math.degrees(float(torch.arccos(((E[:3, :3].trace() - 1) / 2).clamp(-1, 1))))


@pytest.mark.parametrize(
    "seed, trans_m, rot_deg, terms",
    [(0, 0.02, 2.0, "joint"), (1, 0.05, 5.0, "joint"), (2, 0.0, 5.0, "joint"), (3, 0.03, 5.0, "geometric"), (4, 0.03, 3.0, "photometric")],
)
def test_known_motion_is_recovered(room, seed, trans_m, rot_deg, terms):
    P = room.camera_pose(0)
    dT = motion(seed, trans_m, rot_deg)
    ref, cur = view(room, P), view(room, P @ dT)
    cfg = OdometryConfig(photometric=terms != "geometric", geometric=terms != "photometric")
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K(), config=cfg)
    t_err, r_err = pose_error(res.T_ref_cur, dT)  # c2w_cur = c2w_ref @ T_ref_cur
    assert t_err < 1.0 and r_err < 0.05, (t_err, r_err, res)
    assert res.converged and res.ok and res.inlier_ratio > 0.9 and res.overlap > 0.7
    assert len(res.iterations) == cfg.levels
    assert math.isnan(res.rms_geometric) == (terms == "photometric") and math.isnan(res.rms_photometric) == (terms == "geometric")


@pytest.mark.parametrize("terms, tol_mm, tol_deg", [("joint", 1.0, 0.05), ("geometric", 1.0, 0.05), ("photometric", 2.0, 0.1)])
@pytest.mark.parametrize("pick", ["grid", "gradient", "split"])
def test_known_motion_is_recovered_from_a_sparse_pick(room, terms, tol_mm, tol_deg, pick):
    """With one pixel in each 3x3 tile (max_points 2000 of 19k), each pick recovers a known motion.
    Colour alone ends 0.3-1.7 mm off with either pick on this noise-free 8-bit room (seeds 5-9: its
    aliased edges), the depth terms within 0.05 mm."""
    P = room.camera_pose(0)
    dT = motion(5, 0.03, 3.0)
    ref, cur = view(room, P), view(room, P @ dT)
    cfg = OdometryConfig(photometric=terms != "geometric", geometric=terms != "photometric", max_points=2000, pick=pick)
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K(), config=cfg)
    t_err, r_err = pose_error(res.T_ref_cur, dT)
    assert t_err < tol_mm and r_err < tol_deg, (t_err, r_err, res)
    assert res.ok


@pytest.mark.parametrize("term, same_as", [("photometric", "gradient"), ("geometric", "grid")])
def test_the_split_pick_gives_each_term_its_own_pick(room, term, same_as):
    """pick=split tracks the union of both picks, the photometric term on the gradient's pixels and
    point-to-plane on the grid's: each term alone lands exactly where its own pick lands (another pixel set does not)."""
    P = room.camera_pose(0)
    dT = motion(6, 0.03, 3.0)
    ref, cur = view(room, P), view(room, P @ dT)

    def solve(pick: str, max_points: int = 2000) -> torch.Tensor:
        cfg = OdometryConfig(photometric=term == "photometric", geometric=term == "geometric", max_points=max_points, pick=pick)
        return rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K(), config=cfg).T_ref_cur

    split = solve("split")
    torch.testing.assert_close(split, solve(same_as), atol=1e-7, rtol=0)
    assert (split - solve(same_as, 1000)).abs().max() > 1e-6  # another pixel set moves the pose measurably


def test_parallax_pixels_vanish_at_the_median_depth():
    z = torch.tensor([1.0, 2.0, 4.0])
    px = parallax_pixels(z, focal=500.0, baseline=0.025)
    assert torch.allclose(px, 500.0 * 0.025 * torch.tensor([0.5, 0.0, 0.25]))
    assert parallax_pixels(torch.empty(0), 500.0, 0.025).numel() == 0


def test_colour_parallax_only_widens_the_photometric_scale(room):
    """On registered colour the unmodelled-baseline term costs the alignment nothing: same motion recovered."""
    P, dT = room.camera_pose(0), motion(6, 0.03, 3.0)
    ref, cur = view(room, P), view(room, P @ dT)
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K(), config=OdometryConfig(colour_parallax_m=0.025))
    t_err, r_err = pose_error(res.T_ref_cur, dT)
    assert t_err < 1.0 and r_err < 0.05 and res.ok, (t_err, r_err, res)


def test_initial_guess_is_used(room):
    P, dT = room.camera_pose(0), motion(5, 0.03, 4.0)
    ref, cur = view(room, P), view(room, P @ dT)
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K(), T_init=dT)
    cold = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K())
    assert res.ok and sum(res.iterations) < sum(cold.iterations)
    assert pose_error(res.T_ref_cur, dT)[0] < 1.0


def close_up(seq: SyntheticSequence, t0: float, t1: float, distance: float) -> torch.Tensor:
    """(4, 4) c2w looking at the moving cube's mean position over [t0, t1] from ``distance`` metres."""
    mid = (seq.object_poses(t0)["cube"][:3, 3] + seq.object_poses(t1)["cube"][:3, 3]) / 2
    pos = mid + torch.tensor([0.1, -distance, 0.3], dtype=torch.float64)
    z = (mid - pos) / (mid - pos).norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    x = x / x.norm()
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3], c2w[:3, 3] = torch.stack([x, torch.linalg.cross(z, x), z], 1), pos
    return c2w


def test_dynamic_mask_excludes_the_moving_cube(room):
    P, dT = close_up(room, 0.0, 1.5, 0.55), motion(6, 0.02, 2.0)
    ref, cur = view(room, P, t=0.0), view(room, P @ dT, t=1.5)  # the cube moves ~15 cm in between
    assert 0.4 < ref[2].float().mean() < 0.6 and 0.4 < cur[2].float().mean() < 0.6  # half the image moves
    K = room.intrinsics.K()
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], K, ref_mask=ref[2], cur_mask=cur[2])
    t_err, r_err = pose_error(res.T_ref_cur, dT)
    assert t_err < 1.0 and r_err < 0.05 and res.ok, (t_err, r_err)
    unmasked = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], K)
    assert pose_error(unmasked.T_ref_cur, dT)[0] > 5.0 and not unmasked.ok  # the cube drags it: the mask matters
    everything = torch.ones(H, W, dtype=torch.bool)
    blind = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], K, cur_mask=everything)
    assert not blind.ok and blind.num_valid == 0


def test_depth_colour_time_offset_is_compensated(room):
    """Depth taken at another pose than colour (a 20 ms offset at 60 °/s), in both frames."""
    from tivne.slam.tracking.odometry import OdometryConfig as Cfg
    from tivne.slam.tracking.odometry import frame_pyramid, track_pyramids

    P, dT = room.camera_pose(0), motion(9, 0.02, 3.0)
    ref_cd, cur_cd = motion(10, 0.004, 1.2), motion(11, 0.004, 1.2)  # T_rgb_depth of each frame
    K, cfg = room.intrinsics.K(), Cfg()
    ref_rgb, cur_rgb = view(room, P)[0], view(room, P @ dT)[0]
    ref_depth, cur_depth = view(room, P @ ref_cd)[1], view(room, P @ dT @ cur_cd)[1]
    ref, cur = frame_pyramid(ref_rgb, ref_depth, K, cfg), frame_pyramid(cur_rgb, cur_depth, K, cfg)
    res = track_pyramids(ref, cur, None, cfg, ref_rgb_depth=ref_cd, cur_rgb_depth=cur_cd)
    t_err, r_err = pose_error(res.T_ref_cur, dT)
    assert t_err < 1.0 and r_err < 0.05 and res.ok, (t_err, r_err)
    naive = track_pyramids(ref, cur, None, cfg)
    assert pose_error(naive.T_ref_cur, dT)[1] > 0.1  # ignoring the offset costs ~ the offset's rotation


def test_a_rolling_shutter_pair_is_aligned_once_its_rows_motion_is_modelled(room):
    """Two frames of a camera turning at 60-120 °/s, rows read over 30 ms: as if global, the pose is
    30 mm / 2° off; with each frame's velocity modelled, or the current one read from the estimate and
    the previous frame's pose, under a millimetre."""
    from tivne.slam.tracking.odometry import frame_pyramid, track_pyramids
    from tivne.slam.tracking.sensor import Shutter

    readout, dt = 0.03, 1 / 30
    v_ref = torch.tensor([0.2, 0.0, 0.1, 0.0, 2.0, 0.3], dtype=torch.float64)
    v_cur = torch.tensor([-0.1, 0.2, 0.0, 1.5, -1.0, 0.0], dtype=torch.float64)
    P, dT = room.camera_pose(0), se3_exp(torch.tensor([0.02, -0.01, 0.01, 0.01, 0.03, -0.02], dtype=torch.float64))
    K, cfg = room.intrinsics.K(), OdometryConfig()
    ref = frame_pyramid(*room.render_rolling_shutter(P, v_ref, readout), K, cfg)
    cur = frame_pyramid(*room.render_rolling_shutter(P @ dT, v_cur, readout), K, cfg)
    as_global = pose_error(track_pyramids(ref, cur, None, cfg).T_ref_cur, dT)
    assert as_global[0] > 10.0 and as_global[1] > 1.0, as_global
    known = track_pyramids(ref, cur, None, cfg, shutters=(Shutter(readout, v_cur), Shutter(readout, v_ref)))
    t_err, r_err = pose_error(known.T_ref_cur, dT)
    assert t_err < 1.5 and r_err < 0.05 and known.ok, (t_err, r_err)
    estimated = Shutter(readout, torch.zeros(6, dtype=torch.float64), dT @ se3_exp(-dt * v_cur), dt)
    t_err, r_err = pose_error(track_pyramids(ref, cur, None, cfg, shutters=(estimated, Shutter(readout, v_ref))).T_ref_cur, dT)
    assert t_err < 1.5 and r_err < 0.12, (t_err, r_err)


def test_no_depth_reports_failure(room):
    P = room.camera_pose(0)
    ref, cur = view(room, P), view(room, P @ motion(7, 0.01, 1.0))
    res = rgbd_odometry(ref[0], ref[1], cur[0], torch.zeros(H, W), room.intrinsics.K())
    assert not res.ok and not res.converged and res.num_valid == 0 and res.overlap == 0.0
    res = rgbd_odometry(ref[0], torch.zeros(H, W), cur[0], cur[1], room.intrinsics.K())
    assert not res.ok and res.num_valid == 0


def test_no_overlap_reports_failure(room):
    P = room.camera_pose(0)
    turn = torch.eye(4, dtype=torch.float64)
    turn[:3, :3] = se3_exp(torch.tensor([0, 0, 0, 0, math.pi, 0], dtype=torch.float64))[:3, :3]  # look backwards
    ref, cur = view(room, P), view(room, P @ turn)
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K())
    assert not res.ok and res.inlier_ratio < 0.3


def test_degenerate_plane_is_flagged():
    """A textureless fronto-parallel wall fixes only 3 of 6 degrees of freedom."""
    K = torch.tensor([[128.0, 0, 79.5], [0, 128.0, 59.5], [0, 0, 1]])
    rgb, depth = torch.full((H, W, 3), 0.5), torch.full((H, W), 2.0)
    res = rgbd_odometry(rgb, depth, rgb, depth, K)
    assert res.num_valid > 1000 and not res.ok and res.pose_std > 0.01 and res.condition > 1e6


def test_a_pose_prior_decides_only_what_the_pixels_leave_open():
    """On a textureless fronto-parallel wall the pixels fix depth (z) but not the slide along it (x):
    a prior asking for both gets the slide and loses the depth to the pixels."""
    K = torch.tensor([[128.0, 0, 79.5], [0, 128.0, 59.5], [0, 0, 1]])
    rgb, depth = torch.full((H, W, 3), 0.5), torch.full((H, W), 2.0)
    cfg = OdometryConfig()
    wall = frame_pyramid(rgb, depth, K, cfg)
    T_prior = torch.eye(4, dtype=torch.float64)
    T_prior[:3, 3] = torch.tensor([0.01, 0.0, 0.05], dtype=torch.float64)
    prior = PosePrior(T_prior, torch.eye(6, dtype=torch.float64) * 1e2)
    res = track_pyramids(wall, wall, None, cfg, prior=prior)
    t = res.T_ref_cur[:3, 3]
    assert abs(float(t[0]) - 0.01) < 1e-4 and abs(float(t[2])) < 1e-3, t
    free = track_pyramids(wall, wall, None, cfg)
    assert float(free.T_ref_cur[:3, 3].norm()) < 1e-6  # without the prior nothing moves it


def test_robust_weights_at_known_residuals():
    e = torch.tensor([0.0, 1.0, 1.345, 2.69, -5.38])
    assert torch.allclose(huber_weights(e), torch.tensor([1.0, 1.0, 1.0, 0.5, 0.25]))
    assert torch.allclose(cauchy_weights(torch.tensor([0.0, 2.3849, -2.3849 * 3])), torch.tensor([1.0, 0.5, 0.1]))
    r = torch.randn(200_000, generator=torch.Generator().manual_seed(0)) * 0.03 + 0.2
    r[:20_000] = 5.0  # 10 % gross outliers move the MAD scale by ~15 %, a standard deviation by 50x
    assert abs(float(robust_scale(r, 1e-6)) - 0.03) < 0.006 and float(r.std()) > 1.0
    assert float(robust_scale(torch.zeros(10), 0.01)) == pytest.approx(0.01)  # floor
    assert float(robust_scale(r, 1e-6, mask=torch.arange(r.numel()) >= 20_000)) == pytest.approx(0.03, rel=0.05)


def test_pyramid_shapes_intrinsics_and_invalid_depth(room):
    rgb, depth, mask = view(room, room.camera_pose(0))
    K = room.intrinsics.K()
    levels = build_pyramid(rgb, depth, K, 3, mask)
    assert [tuple(lv.intensity.shape) for lv in levels] == [(120, 160), (60, 80), (30, 40)]
    assert levels[1].warp_image.shape == (1, 3, 60, 80) and levels[2].geometry.shape == (7, 30, 40)
    assert not levels[0].usable[mask].any() and (levels[0].depth[mask] == 0).all()  # dynamic pixels are excluded
    # Coarse pixel (u, v) covers fine pixels 2u, 2u + 1: its ray is the ray through the block centre.
    K1 = downsample_K(K)
    uv = torch.tensor([[10.0, 7.0]])
    assert torch.allclose(backproject(uv, torch.ones(1), K1), backproject(2 * uv + 0.5, torch.ones(1), K), atol=1e-6)
    # Invalid depth never averages in; a block across a depth edge keeps the front surface.
    d = torch.tensor([[1.0, 0.0, 3.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]])
    assert torch.allclose(downsample_depth(d), torch.tensor([[1.0, 1.0, 0.0]]))
    assert downsample_mask(torch.tensor([[True, False], [False, False]])).tolist() == [[True]]


def test_a_tracked_frame_builds_only_what_it_reads(room):
    # A frame tracked against a reference reads its sampled pixels' vertices and normals, computed at
    # those pixels alone; they equal the whole level's, which a reference builds at its first read.
    (rgb0, d0, m0), (rgb1, d1, _) = view(room, room.camera_pose(0)), view(room, room.camera_pose(0) @ motion(5, 0.02, 2.0))
    d1 = d1.clone()
    d1[40:50, 60:90] = 0  # a hole: the normals around it are undefined
    K, cfg = room.intrinsics.K(), OdometryConfig()
    ref, cur = frame_pyramid(rgb0, d0, K, cfg, m0), frame_pyramid(rgb1, d1, K, cfg)
    assert track_pyramids(ref, cur, None, cfg).ok
    assert all(lv.is_built for lv in ref) and not any(lv.is_built for lv in cur)
    for lv in cur:
        pixels = torch.rand(lv.usable.shape, generator=torch.Generator().manual_seed(0)) < 0.5
        pixels[0], pixels[:, -1] = True, True  # the image border: neighbours outside it
        vertices, normals = lv.points(pixels)
        assert not lv.is_built
        assert torch.equal(vertices, lv.geometry[1:4, pixels]) and torch.equal(normals, lv.geometry[4:7, pixels])
        undefined = (normals == 0).all(0)
        assert undefined.any() and not undefined.all()
        assert torch.equal(lv.points(pixels)[1], normals)  # read from the geometry now


def test_a_reference_cut_to_its_object_aligns_as_the_whole_image(room):
    # A stored view of one object keeps its box only: same pixels, rays and values at every level,
    # so aligning the moving cube to it gives the same pose as to the whole image.
    P, dT = close_up(room, 0.0, 0.0, 1.2), motion(9, 0.01, 2.0)
    (rgb0, d0, m0), (rgb1, d1, m1) = view(room, P), view(room, P @ dT)
    K, cfg = room.intrinsics.K(), OdometryConfig()
    ref, cur = frame_pyramid(rgb0, d0, K, cfg, ~m0), frame_pyramid(rgb1, d1, K, cfg, ~m1)
    cut = crop_pyramid(ref, m0)
    assert cut[0].intensity.numel() < 0.8 * ref[0].intensity.numel()
    rows, cols = torch.nonzero(m0.any(1)).flatten(), torch.nonzero(m0.any(0)).flatten()
    for level, (lv, whole) in enumerate(zip(cut, ref)):  # the object's pixels are all kept, with their rays
        assert int(lv.usable.sum()) == int(whole.usable.sum())
        y, x = int(rows[0]) // 2**level, int(cols[0]) // 2**level
        a, b = int(whole.K[1, 2] - lv.K[1, 2]), int(whole.K[0, 2] - lv.K[0, 2])
        assert torch.equal(lv.geometry[:, y - a, x - b], whole.geometry[:, y, x])
    full, part = track_pyramids(ref, cur, None, cfg), track_pyramids(cut, cur, None, cfg)
    assert part.ok and torch.allclose(part.T_ref_cur, full.T_ref_cur, atol=1e-6)  # float32 sums in another order
    assert crop_pyramid(ref, torch.zeros_like(m0)) is ref  # nothing to keep: unchanged


def test_references_aligned_jointly_share_one_pose(room):
    # The current view against a reference and a second view of the same scene from elsewhere, whose
    # pose relative to the reference is known: their normal equations join through the adjoint, so
    # the joint pose is as exact as the single one, and where the reference shows only a strip of the
    # scene the companion's pixels make the pose several times more exact than the strip alone.
    P0 = room.camera_pose(0)
    P1, dT = P0 @ motion(11, 0.04, 4.0), motion(12, 0.02, 2.0)
    K, cfg = room.intrinsics.K(), OdometryConfig()
    pyr = [frame_pyramid(*view(room, P)[:2], K, cfg) for P in (P0, P1, P0 @ dT)]
    T_other_ref = invert_pose(P1) @ P0
    joint = track_pyramids(pyr[0], pyr[2], None, cfg, also=((pyr[1], T_other_ref),))
    t_err, r_err = pose_error(joint.T_ref_cur, dT)
    assert joint.ok and t_err < 1.0 and r_err < 0.05, (t_err, r_err)
    strip = torch.ones(H, W, dtype=torch.bool)
    strip[:, 70:90] = False  # the reference keeps a 20-pixel column
    narrow = frame_pyramid(*view(room, P0)[:2], K, cfg, strip)
    alone = pose_error(track_pyramids(narrow, pyr[2], None, cfg).T_ref_cur, dT)
    helped = pose_error(track_pyramids(narrow, pyr[2], None, cfg, also=((pyr[1], T_other_ref),)).T_ref_cur, dT)
    assert helped[0] < 0.5 * alone[0] and helped[1] < 0.5 * alone[1], (alone, helped)


def test_gradients_and_normals_of_known_surfaces():
    u = torch.arange(40.0)[None].expand(30, 40)
    g = image_gradients(0.01 * u)
    assert torch.allclose(g[0, :, 1:-1], torch.full((30, 38), 0.01)) and g[1].abs().max() < 1e-7
    K = torch.tensor([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    wall = backproject(torch.stack([u, torch.arange(30.0)[:, None].expand(30, 40)], -1), torch.full((30, 40), 2.0), K)
    n = vertex_normals(wall.permute(2, 0, 1), torch.ones(30, 40, dtype=torch.bool), 50.0)
    assert torch.allclose(n[:, 1:-1, 1:-1], torch.tensor([0.0, 0.0, -1.0])[:, None, None].expand(3, 28, 38), atol=1e-5)
    assert (n[:, 0] == 0).all()  # no neighbour beyond the border: undefined


def test_normal_equations_match_float64():
    rows = torch.randn(7, 10_000, generator=torch.Generator().manual_seed(1))
    w = torch.rand(10_000, generator=torch.Generator().manual_seed(2))
    H, g = normal_equations(rows, w, block=1024)
    A = rows.double()
    assert torch.allclose(H, (A[:6] * w.double()) @ A[:6].T, rtol=1e-5) and torch.allclose(g, A[:6] @ (w.double() * A[6]), rtol=1e-5)
    assert H.dtype == torch.float64


def test_se3_step_matches_geometry():
    for scale in (0.0, 1e-9, 1e-3, 0.5, 3.0):
        xi = torch.randn(6, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * scale
        assert torch.allclose(se3_step(xi), se3_exp(xi), atol=1e-12)


def test_config_rejects_nonsense():
    with pytest.raises(ValueError):
        OdometryConfig(photometric=False, geometric=False)
    with pytest.raises(ValueError):
        OdometryConfig(robust="l2")
    with pytest.raises(ValueError):
        OdometryConfig(geometric_scale="guess")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(room):
    P, dT = room.camera_pose(0), motion(8, 0.02, 2.0)
    ref, cur = view(room, P), view(room, P @ dT)
    K = room.intrinsics.K()
    res = rgbd_odometry(*(x.cuda() for x in (ref[0], ref[1], cur[0], cur[1], K)))
    assert res.T_ref_cur.is_cuda and pose_error(res.T_ref_cur.cpu(), dT)[0] < 1.0


def test_information_is_the_final_normal_matrix(room):
    """OdometryResult.information: the 6x6 JᵀWJ its pose σ and condition number are taken from,
    and it predicts the solution's sensitivity: more weight on translation than a degenerate system."""
    P = room.camera_pose(0)
    dT = motion(7, 0.02, 2.0)
    ref, cur = view(room, P), view(room, P @ dT)
    res = rgbd_odometry(ref[0], ref[1], cur[0], cur[1], room.intrinsics.K())
    info = res.information
    assert info.shape == (6, 6) and info.dtype == torch.float64
    assert torch.allclose(info, info.T, rtol=0, atol=1e-5 * float(info.abs().max()))  # float32 partial sums
    eig = torch.linalg.eigvalsh(info)
    assert float(eig[0]) > 0
    assert res.pose_std == pytest.approx(1.0 / math.sqrt(float(eig[0])), rel=1e-6)
    assert res.condition == pytest.approx(float(eig[-1] / eig[0]), rel=1e-6)
