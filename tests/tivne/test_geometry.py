"""Per-function tests of tivne.geometry (kornia style: one small test class per function)."""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck

from data_modules.frame import Intrinsics
from tivne import geometry as G

F64 = torch.float64


@pytest.fixture
def intr() -> Intrinsics:
    return Intrinsics(fx=525.0, fy=520.5, cx=319.5, cy=239.25, width=640, height=480)


def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """(n, 3, 3) float64 random proper rotations."""
    q = torch.randn(n, 4, generator=gen, dtype=F64)
    return G.quat_to_matrix(q)


def random_poses(n: int, gen: torch.Generator) -> torch.Tensor:
    """(n, 4, 4) float64 random rigid transforms."""
    T = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    T[:, :3, :3] = random_rotations(n, gen)
    T[:, :3, 3] = torch.randn(n, 3, generator=gen, dtype=F64)
    return T


def twists_with_angles(angles: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """(n, 6) twists (v, w) with random axes and the given rotation angles (n,)."""
    axis = torch.randn(len(angles), 3, generator=gen, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    v = torch.randn(len(angles), 3, generator=gen, dtype=F64)
    return torch.cat([v, axis * angles[:, None]], dim=-1)


class TestIntrinsics:
    def test_round_trip(self, intr):
        K = G.intrinsics_to_K(intr, dtype=F64)
        assert K.shape == (3, 3) and K.dtype == F64
        assert torch.equal(K[2], torch.tensor([0.0, 0.0, 1.0], dtype=F64))
        assert G.K_to_intrinsics(K, intr.width, intr.height) == intr


class TestPixelGrid:
    def test_shape_and_order(self):
        uv = G.pixel_grid(3, 5)
        assert uv.shape == (3, 5, 2)
        assert uv[2, 4].tolist() == [4.0, 2.0]  # (u = column, v = row)


class TestPixelToRay:
    def test_z_is_one_and_principal_point(self, intr):
        K = G.intrinsics_to_K(intr)
        uv = G.pixel_grid(intr.height, intr.width)
        rays = G.pixel_to_ray(uv, K)
        assert rays.shape == (intr.height, intr.width, 3)
        assert torch.all(rays[..., 2] == 1)
        centre = G.pixel_to_ray(torch.tensor([intr.cx, intr.cy]), K)
        assert torch.allclose(centre, torch.tensor([0.0, 0.0, 1.0]))


class TestBackprojectProject:
    def test_round_trip(self, intr):
        gen = torch.Generator().manual_seed(0)
        K = G.intrinsics_to_K(intr, dtype=F64)
        uv = torch.rand(7, 11, 2, generator=gen, dtype=F64) * torch.tensor([intr.width, intr.height], dtype=F64)
        depth = 0.3 + 5 * torch.rand(7, 11, generator=gen, dtype=F64)
        pts = G.backproject(uv, depth, K)
        assert pts.shape == (7, 11, 3)
        assert torch.allclose(pts[..., 2], depth)
        uv2, z = G.project(pts, K)
        assert torch.allclose(uv2, uv, atol=1e-9) and torch.allclose(z, depth)

    def test_backproject_depth_invalid_is_origin(self, intr):
        K = G.intrinsics_to_K(intr)
        depth = torch.full((4, 6), 2.0)
        depth[1, 2] = 0.0
        pts = G.backproject_depth(depth, K)
        assert pts.shape == (4, 6, 3)
        assert torch.all(pts[1, 2] == 0) and torch.allclose(pts[0, 0, 2], torch.tensor(2.0))

    def test_project_behind_camera_is_finite(self, intr):
        uv, z = G.project(torch.tensor([[0.1, 0.2, -1.0], [0.0, 0.0, 0.0]]), G.intrinsics_to_K(intr))
        assert torch.isfinite(uv).all() and z.tolist() == [-1.0, 0.0]


class TestRigidTransforms:
    def test_transform_points_matches_homogeneous(self):
        gen = torch.Generator().manual_seed(1)
        T = random_poses(1, gen)[0]
        p = torch.randn(10, 3, generator=gen, dtype=F64)
        ph = torch.cat([p, torch.ones(10, 1, dtype=F64)], -1)
        assert torch.allclose(G.transform_points(T, p), (ph @ T.T)[:, :3])

    def test_transform_points_batched(self):
        gen = torch.Generator().manual_seed(2)
        T = random_poses(5, gen)
        p = torch.randn(5, 3, generator=gen, dtype=F64)
        out = G.transform_points(T, p)
        for i in range(5):
            assert torch.allclose(out[i], G.transform_points(T[i], p[i]))

    def test_invert_and_compose_identities(self):
        gen = torch.Generator().manual_seed(3)
        A, B, C = random_poses(3, gen)
        eye = torch.eye(4, dtype=F64)
        assert torch.allclose(G.compose(A, G.invert_pose(A)), eye, atol=1e-12)
        assert torch.allclose(G.compose(G.invert_pose(A), A), eye, atol=1e-12)
        assert torch.allclose(G.invert_pose(A), torch.linalg.inv(A), atol=1e-12)
        assert torch.allclose(G.invert_pose(G.compose(A, B)), G.compose(G.invert_pose(B), G.invert_pose(A)), atol=1e-12)
        assert torch.allclose(G.compose(A, B, C), A @ B @ C)
        assert torch.equal(G.compose(A), A)
        p = torch.randn(4, 3, generator=gen, dtype=F64)
        assert torch.allclose(G.transform_points(G.invert_pose(A), G.transform_points(A, p)), p, atol=1e-12)

    def test_invert_batched(self):
        T = random_poses(6, torch.Generator().manual_seed(4)).reshape(2, 3, 4, 4)
        assert torch.allclose(G.invert_pose(T) @ T, torch.eye(4, dtype=F64).expand(2, 3, 4, 4), atol=1e-12)


class TestSe3ExpLog:
    def test_identity(self):
        assert torch.allclose(G.se3_exp(torch.zeros(6, dtype=F64)), torch.eye(4, dtype=F64))
        assert torch.allclose(G.se3_log(torch.eye(4, dtype=F64)), torch.zeros(6, dtype=F64))

    def test_pure_translation_and_rotation(self):
        T = G.se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0], dtype=F64))
        assert torch.allclose(T[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=F64))
        R = G.se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2], dtype=F64))[:3, :3]
        Rz = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
        assert torch.allclose(R, Rz, atol=1e-12)

    @pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-4, 0.5, 2.0, math.pi - 1e-3, math.pi - 1e-6])
    def test_round_trip(self, angle):
        gen = torch.Generator().manual_seed(5)
        xi = twists_with_angles(torch.full((8,), angle, dtype=F64), gen)
        T = G.se3_exp(xi)
        assert T.shape == (8, 4, 4)
        R = T[:, :3, :3]
        assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(8, 3, 3), atol=1e-12)
        assert torch.allclose(torch.linalg.det(R), torch.ones(8, dtype=F64))
        assert torch.allclose(G.se3_log(T), xi, atol=1e-8)

    def test_round_trip_at_pi(self):
        # At exactly pi the twist is ambiguous (w or -w); exp(log(T)) must still give T back.
        xi = twists_with_angles(torch.full((8,), math.pi, dtype=F64), torch.Generator().manual_seed(6))
        T = G.se3_exp(xi)
        assert torch.allclose(G.se3_exp(G.se3_log(T)), T, atol=1e-8)

    def test_random_pose_log_exp(self):
        T = random_poses(16, torch.Generator().manual_seed(7))
        assert torch.allclose(G.se3_exp(G.se3_log(T)), T, atol=1e-10)

    def test_batch_shape(self):
        xi = torch.randn(2, 3, 6, dtype=F64) * 0.3
        T = G.se3_exp(xi)
        assert T.shape == (2, 3, 4, 4)
        assert G.se3_log(T).shape == (2, 3, 6)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_gradient_finite_at_zero(self, dtype):
        xi = torch.zeros(6, dtype=dtype, requires_grad=True)
        T = G.se3_exp(xi)
        # A loss that depends on every entry, so every component of the gradient is exercised.
        (T * torch.arange(16, dtype=dtype).reshape(4, 4)).sum().backward()
        assert torch.isfinite(xi.grad).all()
        # d exp / d xi at 0 is the generator basis: d T[0, 3] / d v_x = 1, d T[1, 0] / d w_z = 1.
        for (r, c), k in [((0, 3), 0), ((1, 3), 1), ((2, 3), 2), ((2, 1), 3), ((0, 2), 4), ((1, 0), 5)]:
            x = torch.zeros(6, dtype=dtype, requires_grad=True)
            (g,) = torch.autograd.grad(G.se3_exp(x)[r, c], x)
            expected = torch.zeros(6, dtype=dtype)
            expected[k] = 1.0
            assert torch.allclose(g, expected), (r, c, g)

    def test_constant_input_gives_constant_output(self):
        # kornia wraps constant inputs in nn.Parameter; se3_exp / se3_log must not leak that.
        T = G.se3_exp(torch.randn(3, 6, dtype=F64))
        assert not T.requires_grad and not G.se3_log(T).requires_grad
        xi = torch.randn(6, dtype=F64, requires_grad=True)
        assert G.se3_exp(xi).requires_grad and G.se3_log(G.se3_exp(xi)).requires_grad
        with torch.no_grad():
            assert not G.se3_exp(xi).requires_grad

    def test_gradcheck_random(self):
        xi = (0.7 * torch.randn(3, 6, generator=torch.Generator().manual_seed(8), dtype=F64)).requires_grad_()
        assert gradcheck(G.se3_exp, (xi,), eps=1e-6, atol=1e-6)

    def test_gradcheck_zero(self):
        xi = torch.zeros(1, 6, dtype=F64, requires_grad=True)
        assert gradcheck(G.se3_exp, (xi,), eps=1e-6, atol=1e-6)

    def test_gradcheck_log(self):
        T = G.se3_exp(0.5 * torch.randn(2, 6, generator=torch.Generator().manual_seed(9), dtype=F64))
        # Perturbing all 16 entries leaves SE(3); the analytic and numeric Jacobians agree anyway
        # because both differentiate the same closed-form expression of the entries.
        assert gradcheck(G.se3_log, (T.detach().requires_grad_(),), eps=1e-6, atol=1e-5)


class TestDataLayerReExports:
    def test_pose_helpers_are_the_data_layer_functions(self):
        from data_modules import poses

        for name in ("quat_to_matrix", "matrix_to_quat", "pose_from_tq", "orthonormalize_pose"):
            assert getattr(G, name) is getattr(poses, name), name


def test_eigen_range_of_an_information_matrix_and_of_a_degenerate_one():
    H = torch.diag(torch.tensor([4.0, 1.0, 9.0, 2.0, 3.0, 5.0], dtype=torch.float64))
    assert G.eigen_range(H) == (1.0, 9.0)
    bad = H.clone()
    bad[0, 0] = float("nan")  # an alignment whose linearisation went non-finite: no pose information
    assert G.eigen_range(bad) == (0.0, 0.0)
    assert G.eigen_range(torch.full((6, 6), float("inf"), dtype=torch.float64)) == (0.0, 0.0)


def test_depth_lookup_gives_each_point_its_pixel_and_the_nearest_depth_around_it():
    depth = torch.full((4, 6), 3.0)
    depth[:, :2] = 1.0  # a near surface over the first two columns
    depth[0, 5] = 0.0  # a hole
    K = torch.tensor([[2.0, 0.0, 2.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]])
    # pixels (u, v) = (2, 1): beside the near surface; (4, 1): inside the far one; (5, 0): the hole; off the image; behind
    points = torch.tensor([[0.0, 0.0, 2.0], [2.0, 0.0, 2.0], [3.0, -1.0, 2.0], [9.0, 0.0, 2.0], [0.0, 0.0, -1.0]])
    z, inside, nearest, centre = G.depth_lookup(points, depth, K)
    assert z.tolist() == [2.0, 2.0, 2.0, 2.0, -1.0]
    assert inside.tolist() == [True, True, True, False, False]
    assert nearest[:3].tolist() == [1.0, 3.0, 3.0] and torch.isinf(nearest[3:]).all()
    assert centre.tolist() == [3.0, 3.0, 0.0, 0.0, 0.0]
