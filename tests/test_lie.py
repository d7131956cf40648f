"""warpbags.lie: SO(3)/SE(3) exp and log, the geodesic angle, and the Warp pose transform against them (CPU, float64)."""

from __future__ import annotations

import math

import pytest
import torch
from random_poses import F64, generator, random_rotations, random_viewmats, skew_reference, twist_matrix, unit_vectors

from warpbags.lie import rotation_between, rotation_error_deg, se3_exp, so3_exp, so3_log
from warpbags.wrapper import apply_pose_deltas  # the one implementation (Warp), checked here against torch's maths


# Angles (radians) that exercise the series branch (0 .. 0.5), its boundary, the closed form and the region
# around pi. The series/closed-form switch is at theta = 0.5.
ANGLES = [
    0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 0.5 - 1e-9, 0.5, 0.5 + 1e-9, 1.0, 2.0, math.pi - 1e-3, math.pi - 1e-8, math.pi
]


# ----------------------------------------------------------------------------------------------- exp maps


def test_exp_at_zero_is_identity_and_jacobian_is_the_generators():
    zero3 = torch.zeros(3, dtype=F64)
    assert torch.equal(so3_exp(zero3), torch.eye(3, dtype=F64))
    assert torch.equal(se3_exp(torch.zeros(6, dtype=F64)), torch.eye(4, dtype=F64))

    jac_so3 = torch.autograd.functional.jacobian(so3_exp, zero3)  # [3, 3, 3]
    jac_se3 = torch.autograd.functional.jacobian(se3_exp, torch.zeros(6, dtype=F64))  # [4, 4, 6]
    for k in range(3):
        e_k = torch.zeros(3, dtype=F64)
        e_k[k] = 1.0
        torch.testing.assert_close(jac_so3[..., k], skew_reference(e_k), rtol=0, atol=0)
    for k in range(6):
        e_k = torch.zeros(6, dtype=F64)
        e_k[k] = 1.0
        torch.testing.assert_close(jac_se3[..., k], twist_matrix(e_k), rtol=0, atol=0)


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_gradcheck(angle):
    gen = generator(1)
    axis = unit_vectors(2, gen)
    omega = (axis * angle).requires_grad_(True)
    assert torch.autograd.gradcheck(so3_exp, (omega,), eps=1e-6, atol=1e-7, rtol=1e-6)
    xi = torch.cat([axis * angle, torch.randn(2, 3, generator=gen, dtype=F64)], dim=-1).requires_grad_(True)
    assert torch.autograd.gradcheck(se3_exp, (xi,), eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_gradient_at_tiny_and_zero_angles_is_finite(angle):
    omega = (unit_vectors(4, generator(2)) * angle).requires_grad_(True)
    xi = torch.cat([omega, torch.ones(4, 3, dtype=F64)], dim=-1)
    (se3_exp(xi) * torch.randn(4, 4, 4, generator=generator(3), dtype=F64)).sum().backward()
    assert torch.isfinite(omega.grad).all()


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-14), (torch.float32, 1e-6)])
def test_so3_exp_matches_matrix_exp(dtype, atol):
    gen = generator(4)
    omega = torch.cat([unit_vectors(1, gen) * a for a in ANGLES] + [torch.randn(50, 3, generator=gen, dtype=F64) * 2])
    expected = torch.linalg.matrix_exp(skew_reference(omega))
    torch.testing.assert_close(so3_exp(omega.to(dtype)).to(F64), expected, rtol=0, atol=atol)


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-13), (torch.float32, 4e-6)])
def test_se3_exp_matches_matrix_exp_of_twist(dtype, atol):
    gen = generator(5)
    omega = torch.cat([unit_vectors(1, gen) * a for a in ANGLES] + [torch.randn(50, 3, generator=gen, dtype=F64) * 2])
    xi = torch.cat([omega, torch.randn(omega.shape[0], 3, generator=gen, dtype=F64)], dim=-1)
    expected = torch.linalg.matrix_exp(twist_matrix(xi))
    actual = se3_exp(xi.to(dtype))
    assert actual.dtype == dtype
    torch.testing.assert_close(actual.to(F64), expected, rtol=0, atol=atol)


def test_se3_exp_float32_jacobian_near_zero():
    """Below `_SERIES_THETA2` the coefficients come from their series: the closed form's (theta - sin theta) /
    theta^3 cancels in float32 near 0, and its gradient at theta = 1e-3 is off by far more than float32 rounding
    (only values were checked in float32)."""
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    xi = torch.cat([axis / axis.norm() * 1e-3, torch.tensor([0.7, -1.2, 0.4], dtype=F64)])
    expected = torch.autograd.functional.jacobian(se3_exp, xi)
    actual = torch.autograd.functional.jacobian(se3_exp, xi.float())
    torch.testing.assert_close(actual.double(), expected, rtol=0, atol=1e-6)


def test_exp_is_batched_over_leading_dimensions():
    xi = torch.randn(2, 5, 6, generator=generator(6), dtype=F64)
    batched = se3_exp(xi)
    assert batched.shape == (2, 5, 4, 4)
    torch.testing.assert_close(batched[1, 3], se3_exp(xi[1, 3]), rtol=0, atol=1e-15)
    assert so3_exp(xi[..., :3]).shape == (2, 5, 3, 3)
    assert so3_log(so3_exp(xi[..., :3])).shape == (2, 5, 3)


# ----------------------------------------------------------------------------------------------- log map


@pytest.mark.parametrize("angle", [a for a in ANGLES if a < math.pi])
def test_log_inverts_exp(angle):
    omega = unit_vectors(8, generator(7)) * angle
    recovered = so3_log(torch.linalg.matrix_exp(skew_reference(omega)))
    torch.testing.assert_close(recovered, omega, rtol=0, atol=1e-12)


def test_exp_inverts_log_for_random_rotations_and_at_pi():
    gen = generator(8)
    axes = unit_vectors(6, gen)
    rotations = torch.cat([random_rotations(200, gen), torch.linalg.matrix_exp(skew_reference(axes * math.pi))])
    omega = so3_log(rotations)
    assert (omega.norm(dim=-1) <= math.pi + 1e-12).all()
    torch.testing.assert_close(so3_exp(omega), rotations, rtol=0, atol=1e-13)
    # At exactly pi the axis is recovered up to sign.
    at_pi = omega[-6:] / math.pi
    torch.testing.assert_close((at_pi * axes).sum(-1).abs(), torch.ones(6, dtype=F64), rtol=0, atol=1e-12)


def test_log_float32_round_trip():
    rotations = random_rotations(200, generator(9)).float()
    torch.testing.assert_close(so3_exp(so3_log(rotations)), rotations, rtol=0, atol=2e-6)


# ----------------------------------------------------------------------------------------------- poses


def test_apply_pose_deltas_order_and_left_composition():
    gen = generator(10)
    viewmats = random_viewmats(3, gen)

    # Translation part last: [0, 0, 0, v] shifts the camera-frame translation by v, rotation untouched.
    shift = torch.tensor([[0.0, 0.0, 0.0, 1.0, -2.0, 3.0]], dtype=F64).expand(3, 6)
    shifted = apply_pose_deltas(viewmats, shift)
    torch.testing.assert_close(shifted[:, :3, :3], viewmats[:, :3, :3], rtol=0, atol=1e-15)
    torch.testing.assert_close(shifted[:, :3, 3], viewmats[:, :3, 3] + shift[:, 3:], rtol=0, atol=1e-15)

    # Rotation part first, applied on the left (camera frame): [a, 0, 0, 0, 0, 0] -> Rx(a) @ viewmat.
    a = 0.3
    rot_x = torch.eye(4, dtype=F64)
    rot_x[1:3, 1:3] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=F64)
    turned = apply_pose_deltas(viewmats, torch.tensor([a, 0, 0, 0, 0, 0], dtype=F64).expand(3, 6))
    torch.testing.assert_close(turned, rot_x @ viewmats, rtol=0, atol=1e-14)

    deltas = torch.randn(3, 6, generator=gen, dtype=F64)
    expected = torch.linalg.matrix_exp(twist_matrix(deltas)) @ viewmats
    torch.testing.assert_close(apply_pose_deltas(viewmats, deltas), expected, rtol=0, atol=1e-12)


def test_zero_deltas_leave_poses_unchanged_and_have_finite_gradients():
    viewmats = random_viewmats(4, generator(11))
    deltas = torch.zeros(4, 6, dtype=F64, requires_grad=True)
    out = apply_pose_deltas(viewmats, deltas)
    torch.testing.assert_close(out, viewmats, rtol=0, atol=1e-15)
    out.square().sum().backward()
    assert torch.isfinite(deltas.grad).all() and deltas.grad.abs().sum() > 0


# ----------------------------------------------------------------------------------------------- rotation error


def test_rotation_error_deg_known_angles_including_tiny_and_pi():
    gen = generator(13)
    angles = torch.tensor([0.0, 1e-8, 1e-4, 0.7, 2.5, math.pi - 1e-7, math.pi], dtype=F64)
    axes = unit_vectors(angles.shape[0], gen)
    base = random_rotations(angles.shape[0], gen)
    turned = torch.linalg.matrix_exp(skew_reference(axes * angles[:, None])) @ base
    errors = rotation_error_deg(turned, base)
    torch.testing.assert_close(errors, torch.rad2deg(angles), rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(rotation_error_deg(base, turned), errors, rtol=1e-7, atol=1e-12)


def test_rotation_error_deg_resolves_small_angles_in_float32():
    # acos((tr - 1) / 2) cannot resolve 1e-3 degrees in float32 (it returns 0 or ~0.02 degrees).
    axes = unit_vectors(10, generator(14))
    rotations = torch.linalg.matrix_exp(skew_reference(axes * math.radians(1e-3))).float()
    errors = rotation_error_deg(rotations, torch.eye(3).expand(10, 3, 3))
    torch.testing.assert_close(errors, torch.full((10,), 1e-3), rtol=1e-3, atol=0)


def test_rotation_between_opposite_vectors_is_a_half_turn():
    """The cross product of opposite vectors vanishes: the identity came back, silently, for (0, 0, 1) -> (0, 0, -1)."""
    for source in ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.8, 0.0]):
        source = torch.tensor(source, dtype=torch.float64)
        rotation = rotation_between(source, -source)
        torch.testing.assert_close(rotation @ source, -source, rtol=0, atol=1e-12)
        torch.testing.assert_close(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12)
