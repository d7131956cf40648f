"""Tests for warpbags.pose: exp/log maps, pose noise, Umeyama, alignment and pose errors (CPU, float64)."""

from __future__ import annotations

import math

import pytest
import torch

from warpbags.pose import (
    Sim3,
    align_viewmats,
    azimuth_order,
    camera_centers,
    interpolated_viewmats,
    perturb_viewmats,
    pose_errors,
    rotation_error_deg,
    se3_exp,
    so3_exp,
    so3_log,
    turntable_viewmats,
    umeyama,
)
from warpbags.wrapper import apply_pose_deltas  # the one implementation (Warp), checked here against torch's maths

F64 = torch.float64

# Angles (radians) that exercise the series branch (0 .. 0.5), its boundary, the closed form and the region
# around pi. The series/closed-form switch is at theta = 0.5.
ANGLES = [
    0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 0.5 - 1e-9, 0.5, 0.5 + 1e-9, 1.0, 2.0, math.pi - 1e-3, math.pi - 1e-8, math.pi
]


def _generator(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _unit_vectors(n: int, gen: torch.Generator) -> torch.Tensor:
    vectors = torch.randn(n, 3, generator=gen, dtype=F64)
    return vectors / vectors.norm(dim=-1, keepdim=True)


def _skew_reference(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix written out entry by entry (independent of the module's helper)."""
    k = torch.zeros(*v.shape[:-1], 3, 3, dtype=v.dtype)
    k[..., 0, 1], k[..., 0, 2] = -v[..., 2], v[..., 1]
    k[..., 1, 0], k[..., 1, 2] = v[..., 2], -v[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -v[..., 1], v[..., 0]
    return k


def _twist_matrix(xi: torch.Tensor) -> torch.Tensor:
    """4x4 matrix [[skew(w), v], [0, 0]] of a twist [w, v]."""
    t = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    t[..., :3, :3] = _skew_reference(xi[..., :3])
    t[..., :3, 3] = xi[..., 3:]
    return t


def _random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """Rotations from the matrix exponential (not from so3_exp, so tests of so3_exp stay independent)."""
    omega = torch.randn(n, 3, generator=gen, dtype=F64) * 1.5
    return torch.linalg.matrix_exp(_skew_reference(omega))


def _random_viewmats(n: int, gen: torch.Generator) -> torch.Tensor:
    rotations = _random_rotations(n, gen)
    centers = torch.randn(n, 3, generator=gen, dtype=F64) * 3.0
    viewmats = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    viewmats[:, :3, :3] = rotations
    viewmats[:, :3, 3] = -(rotations @ centers[..., None])[..., 0]
    return viewmats


def _random_sim3(gen: torch.Generator, scale: float = 2.7) -> Sim3:
    rotation = _random_rotations(1, gen)[0]
    translation = torch.randn(3, generator=gen, dtype=F64) * 5.0
    return Sim3(torch.tensor(scale, dtype=F64), rotation, translation)


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
        torch.testing.assert_close(jac_so3[..., k], _skew_reference(e_k), rtol=0, atol=0)
    for k in range(6):
        e_k = torch.zeros(6, dtype=F64)
        e_k[k] = 1.0
        torch.testing.assert_close(jac_se3[..., k], _twist_matrix(e_k), rtol=0, atol=0)


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_gradcheck(angle):
    gen = _generator(1)
    axis = _unit_vectors(2, gen)
    omega = (axis * angle).requires_grad_(True)
    assert torch.autograd.gradcheck(so3_exp, (omega,), eps=1e-6, atol=1e-7, rtol=1e-6)
    xi = torch.cat([axis * angle, torch.randn(2, 3, generator=gen, dtype=F64)], dim=-1).requires_grad_(True)
    assert torch.autograd.gradcheck(se3_exp, (xi,), eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_gradient_at_tiny_and_zero_angles_is_finite(angle):
    omega = (_unit_vectors(4, _generator(2)) * angle).requires_grad_(True)
    xi = torch.cat([omega, torch.ones(4, 3, dtype=F64)], dim=-1)
    (se3_exp(xi) * torch.randn(4, 4, 4, generator=_generator(3), dtype=F64)).sum().backward()
    assert torch.isfinite(omega.grad).all()


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-14), (torch.float32, 1e-6)])
def test_so3_exp_matches_matrix_exp(dtype, atol):
    gen = _generator(4)
    omega = torch.cat([_unit_vectors(1, gen) * a for a in ANGLES] + [torch.randn(50, 3, generator=gen, dtype=F64) * 2])
    expected = torch.linalg.matrix_exp(_skew_reference(omega))
    torch.testing.assert_close(so3_exp(omega.to(dtype)).to(F64), expected, rtol=0, atol=atol)


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-13), (torch.float32, 4e-6)])
def test_se3_exp_matches_matrix_exp_of_twist(dtype, atol):
    gen = _generator(5)
    omega = torch.cat([_unit_vectors(1, gen) * a for a in ANGLES] + [torch.randn(50, 3, generator=gen, dtype=F64) * 2])
    xi = torch.cat([omega, torch.randn(omega.shape[0], 3, generator=gen, dtype=F64)], dim=-1)
    expected = torch.linalg.matrix_exp(_twist_matrix(xi))
    actual = se3_exp(xi.to(dtype))
    assert actual.dtype == dtype
    torch.testing.assert_close(actual.to(F64), expected, rtol=0, atol=atol)


def test_exp_is_batched_over_leading_dimensions():
    xi = torch.randn(2, 5, 6, generator=_generator(6), dtype=F64)
    batched = se3_exp(xi)
    assert batched.shape == (2, 5, 4, 4)
    torch.testing.assert_close(batched[1, 3], se3_exp(xi[1, 3]), rtol=0, atol=1e-15)
    assert so3_exp(xi[..., :3]).shape == (2, 5, 3, 3)
    assert so3_log(so3_exp(xi[..., :3])).shape == (2, 5, 3)


# ----------------------------------------------------------------------------------------------- log map


@pytest.mark.parametrize("angle", [a for a in ANGLES if a < math.pi])
def test_log_inverts_exp(angle):
    omega = _unit_vectors(8, _generator(7)) * angle
    recovered = so3_log(torch.linalg.matrix_exp(_skew_reference(omega)))
    torch.testing.assert_close(recovered, omega, rtol=0, atol=1e-12)


def test_exp_inverts_log_for_random_rotations_and_at_pi():
    gen = _generator(8)
    axes = _unit_vectors(6, gen)
    rotations = torch.cat([_random_rotations(200, gen), torch.linalg.matrix_exp(_skew_reference(axes * math.pi))])
    omega = so3_log(rotations)
    assert (omega.norm(dim=-1) <= math.pi + 1e-12).all()
    torch.testing.assert_close(so3_exp(omega), rotations, rtol=0, atol=1e-13)
    # At exactly pi the axis is recovered up to sign.
    at_pi = omega[-6:] / math.pi
    torch.testing.assert_close((at_pi * axes).sum(-1).abs(), torch.ones(6, dtype=F64), rtol=0, atol=1e-12)


def test_log_float32_round_trip():
    rotations = _random_rotations(200, _generator(9)).float()
    torch.testing.assert_close(so3_exp(so3_log(rotations)), rotations, rtol=0, atol=2e-6)


# ----------------------------------------------------------------------------------------------- poses


def test_apply_pose_deltas_order_and_left_composition():
    gen = _generator(10)
    viewmats = _random_viewmats(3, gen)

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
    expected = torch.linalg.matrix_exp(_twist_matrix(deltas)) @ viewmats
    torch.testing.assert_close(apply_pose_deltas(viewmats, deltas), expected, rtol=0, atol=1e-12)


def test_zero_deltas_leave_poses_unchanged_and_have_finite_gradients():
    viewmats = _random_viewmats(4, _generator(11))
    deltas = torch.zeros(4, 6, dtype=F64, requires_grad=True)
    out = apply_pose_deltas(viewmats, deltas)
    torch.testing.assert_close(out, viewmats, rtol=0, atol=1e-15)
    out.square().sum().backward()
    assert torch.isfinite(deltas.grad).all() and deltas.grad.abs().sum() > 0


def test_camera_centers_map_to_camera_origin():
    viewmats = _random_viewmats(5, _generator(12))
    centers = camera_centers(viewmats)
    homogeneous = torch.cat([centers, torch.ones(5, 1, dtype=F64)], dim=-1)
    in_camera = (viewmats @ homogeneous[..., None])[..., 0]
    torch.testing.assert_close(in_camera[:, :3], torch.zeros(5, 3, dtype=F64), rtol=0, atol=1e-13)
    # A camera at (1, 2, 3) looking down +z with identity rotation has t = -c.
    simple = torch.eye(4, dtype=F64)
    simple[:3, 3] = torch.tensor([-1.0, -2.0, -3.0], dtype=F64)
    torch.testing.assert_close(camera_centers(simple[None])[0], torch.tensor([1.0, 2.0, 3.0], dtype=F64))


# ----------------------------------------------------------------------------------------------- rotation error


def test_rotation_error_deg_known_angles_including_tiny_and_pi():
    gen = _generator(13)
    angles = torch.tensor([0.0, 1e-8, 1e-4, 0.7, 2.5, math.pi - 1e-7, math.pi], dtype=F64)
    axes = _unit_vectors(angles.shape[0], gen)
    base = _random_rotations(angles.shape[0], gen)
    turned = torch.linalg.matrix_exp(_skew_reference(axes * angles[:, None])) @ base
    errors = rotation_error_deg(turned, base)
    torch.testing.assert_close(errors, torch.rad2deg(angles), rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(rotation_error_deg(base, turned), errors, rtol=1e-7, atol=1e-12)


def test_rotation_error_deg_resolves_small_angles_in_float32():
    # acos((tr - 1) / 2) cannot resolve 1e-3 degrees in float32 (it returns 0 or ~0.02 degrees).
    axes = _unit_vectors(10, _generator(14))
    rotations = torch.linalg.matrix_exp(_skew_reference(axes * math.radians(1e-3))).float()
    errors = rotation_error_deg(rotations, torch.eye(3).expand(10, 3, 3))
    torch.testing.assert_close(errors, torch.full((10,), 1e-3), rtol=1e-3, atol=0)


# ----------------------------------------------------------------------------------------------- umeyama / Sim3


@pytest.mark.parametrize("num_points", [3, 10])
def test_umeyama_recovers_known_sim3(num_points):
    gen = _generator(15)
    truth = _random_sim3(gen, scale=2.7)
    src = torch.randn(num_points, 3, generator=gen, dtype=F64)
    scale, rotation, translation = umeyama(src, truth.apply(src))
    torch.testing.assert_close(scale, truth.scale, rtol=1e-12, atol=0)
    torch.testing.assert_close(rotation, truth.rotation, rtol=0, atol=1e-12)
    torch.testing.assert_close(translation, truth.translation, rtol=0, atol=1e-11)


def test_umeyama_without_scale():
    gen = _generator(16)
    rigid = _random_sim3(gen, scale=1.0)
    src = torch.randn(10, 3, generator=gen, dtype=F64)
    scale, rotation, translation = umeyama(src, rigid.apply(src), with_scale=False)
    assert scale.item() == 1.0
    torch.testing.assert_close(rotation, rigid.rotation, rtol=0, atol=1e-12)
    torch.testing.assert_close(translation, rigid.translation, rtol=0, atol=1e-11)
    # With a real scale in the data, the rigid fit keeps s = 1 but still finds the rotation.
    scaled = Sim3(torch.tensor(0.4, dtype=F64), rigid.rotation, rigid.translation)
    scale, rotation, _ = umeyama(src, scaled.apply(src), with_scale=False)
    assert scale.item() == 1.0
    torch.testing.assert_close(rotation, rigid.rotation, rtol=0, atol=1e-12)


def test_umeyama_is_the_least_squares_optimum_under_noise():
    gen = _generator(17)
    truth = _random_sim3(gen, scale=0.6)
    src = torch.randn(12, 3, generator=gen, dtype=F64)
    dst = truth.apply(src) + 0.05 * torch.randn(12, 3, generator=gen, dtype=F64)
    fit = Sim3(*umeyama(src, dst))

    def residual(sim3: Sim3) -> float:
        return (sim3.apply(src) - dst).square().sum().item()

    assert residual(fit) <= residual(truth)
    # Any small perturbation of the fitted parameters increases the residual (first-order optimality).
    for k in range(7):
        step = torch.zeros(7, dtype=F64)
        step[k] = 1e-4
        for sign in (1.0, -1.0):
            rotated = so3_exp(sign * step[:3]) @ fit.rotation
            moved = Sim3(fit.scale * (1 + sign * step[6]), rotated, fit.translation + sign * step[3:6])
            assert residual(moved) > residual(fit)
    assert abs(fit.scale.item() - 0.6) < 0.05


def test_umeyama_fixes_reflections():
    gen = _generator(18)
    src = torch.randn(10, 3, generator=gen, dtype=F64)
    mirrored = src * torch.tensor([1.0, 1.0, -1.0], dtype=F64)  # no proper rotation maps src onto this
    scale, rotation, translation = umeyama(src, mirrored)
    torch.testing.assert_close(torch.det(rotation), torch.tensor(1.0, dtype=F64), rtol=0, atol=1e-12)
    torch.testing.assert_close(rotation @ rotation.T, torch.eye(3, dtype=F64), rtol=0, atol=1e-12)
    # Given the rotation, scale and translation must be the least-squares optimum for it:
    # s = <dst_c, R src_c> / |src_c|^2 on centred points, t = mean(dst) - s R mean(src).
    src_c, dst_c = src - src.mean(0), mirrored - mirrored.mean(0)
    best_scale = (dst_c * (src_c @ rotation.T)).sum() / src_c.square().sum()
    torch.testing.assert_close(scale, best_scale, rtol=1e-12, atol=0)
    torch.testing.assert_close(translation, mirrored.mean(0) - scale * rotation @ src.mean(0), rtol=0, atol=1e-12)


def test_umeyama_rejects_degenerate_input():
    src = torch.randn(5, 3, generator=_generator(19), dtype=F64)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(src[:2], src[:2])
    collinear = torch.linspace(0, 1, 5, dtype=F64)[:, None] * torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    with pytest.raises(ValueError, match="collinear"):
        umeyama(collinear, collinear)
    with pytest.raises(ValueError, match="collinear"):
        umeyama(torch.ones(4, 3, dtype=F64), src[:4])
    with pytest.raises(ValueError, match="same shape"):
        umeyama(src, src[:4])
    nan_src = src.clone()
    nan_src[0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        umeyama(nan_src, src)


def test_sim3_inverse_and_align_viewmats():
    gen = _generator(20)
    sim3 = _random_sim3(gen, scale=1.8)
    viewmats = _random_viewmats(5, gen)
    points = torch.randn(7, 3, generator=gen, dtype=F64)
    torch.testing.assert_close(sim3.inverse().apply(sim3.apply(points)), points, rtol=0, atol=1e-13)

    aligned = align_viewmats(viewmats, sim3)
    torch.testing.assert_close(camera_centers(aligned), sim3.apply(camera_centers(viewmats)), rtol=0, atol=1e-12)
    c2w_aligned = aligned[:, :3, :3].transpose(-1, -2)
    torch.testing.assert_close(c2w_aligned, sim3.rotation @ viewmats[:, :3, :3].transpose(-1, -2), rtol=0, atol=1e-14)
    torch.testing.assert_close(aligned[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(5, 4), rtol=0, atol=0)
    torch.testing.assert_close(align_viewmats(aligned, sim3.inverse()), viewmats, rtol=0, atol=1e-12)
    # Points keep their camera-frame coordinates: the map is a change of world frame (up to scale).
    homogeneous = torch.cat([points, torch.ones(7, 1, dtype=F64)], dim=-1)
    moved = torch.cat([sim3.apply(points), torch.ones(7, 1, dtype=F64)], dim=-1)
    before = (viewmats[0] @ homogeneous.T).T[:, :3]
    after = (aligned[0] @ moved.T).T[:, :3]
    torch.testing.assert_close(after, sim3.scale * before, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------------------------- pose errors


@pytest.mark.parametrize("alignment", ["procrustes", "pairwise"])
@pytest.mark.parametrize("num_cameras", [4, 9])
def test_pose_errors_vanish_after_a_known_sim3(alignment, num_cameras):
    gen = _generator(21)
    reference = _random_viewmats(num_cameras, gen)
    world_change = _random_sim3(gen, scale=0.35)
    estimated = align_viewmats(reference, world_change)  # same cameras, another world frame

    result = pose_errors(estimated, reference, alignment=alignment)
    assert result["rotation_errors_deg"].shape == (num_cameras,)
    assert result["rotation_errors_deg"].max() < 1e-9
    assert result["translation_errors"].max() < 1e-11
    assert result["rotation_error_deg_mean"] < 1e-9 and result["translation_error_median"] < 1e-11
    recovered = result["sim3"]
    expected = world_change.inverse()
    torch.testing.assert_close(recovered.scale, expected.scale, rtol=1e-12, atol=0)
    torch.testing.assert_close(recovered.rotation, expected.rotation, rtol=0, atol=1e-12)
    torch.testing.assert_close(recovered.translation, expected.translation, rtol=0, atol=1e-11)

    unaligned = pose_errors(estimated, reference, alignment="none")
    assert unaligned["translation_error_mean"] > 1.0 and unaligned["rotation_error_deg_mean"] > 1.0


@pytest.mark.parametrize("alignment", ["procrustes", "pairwise"])
def test_pose_errors_are_invariant_to_the_estimated_world_frame(alignment):
    gen = _generator(22)
    reference = _random_viewmats(6, gen)
    noisy = perturb_viewmats(reference, rot_std_deg=3.0, trans_std=0.2, seed=5)
    baseline = pose_errors(noisy, reference, alignment=alignment)
    moved = pose_errors(align_viewmats(noisy, _random_sim3(gen, scale=4.0)), reference, alignment=alignment)
    assert baseline["rotation_error_deg_mean"] > 0.5  # the noise is really there
    torch.testing.assert_close(moved["rotation_errors_deg"], baseline["rotation_errors_deg"], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(moved["translation_errors"], baseline["translation_errors"], rtol=1e-9, atol=1e-11)


def test_pose_errors_summary_statistics():
    gen = _generator(23)
    reference = _random_viewmats(5, gen)
    noisy = perturb_viewmats(reference, rot_std_deg=5.0, trans_std=0.3, seed=1)
    result = pose_errors(noisy, reference, alignment="none")
    rotation, translation = result["rotation_errors_deg"], result["translation_errors"]
    assert result["rotation_error_deg_mean"] == pytest.approx(rotation.mean().item())
    assert result["rotation_error_deg_median"] == pytest.approx(rotation.sort().values[2].item())
    assert result["translation_error_mean"] == pytest.approx(translation.mean().item())
    assert result["translation_error_median"] == pytest.approx(translation.sort().values[2].item())
    expected_translation = (camera_centers(noisy) - camera_centers(reference)).norm(dim=-1)
    torch.testing.assert_close(translation, expected_translation, rtol=0, atol=1e-12)


def test_pairwise_alignment_matches_brute_force_over_pairs():
    gen = _generator(24)
    reference = _random_viewmats(5, gen)
    noisy = perturb_viewmats(reference, rot_std_deg=8.0, trans_std=0.5, seed=3)
    result = pose_errors(noisy, reference, alignment="pairwise")

    centers_est, centers_ref = camera_centers(noisy), camera_centers(reference)
    best = math.inf
    for i in range(5):
        rotation = reference[i, :3, :3].T @ noisy[i, :3, :3]  # c2w_ref_i @ c2w_est_i^T
        for j in range(5):
            if i == j:
                continue
            scale = (centers_ref[i] - centers_ref[j]).norm() / (centers_est[i] - centers_est[j]).norm()
            sim3 = Sim3(scale, rotation, centers_ref[i] - scale * rotation @ centers_est[i])
            candidate = pose_errors(align_viewmats(noisy, sim3), reference, alignment="none")
            best = min(best, candidate["rotation_error_deg_mean"] * candidate["translation_error_mean"])
            # By construction camera i coincides with its reference.
            assert candidate["rotation_errors_deg"][i] < 1e-9 and candidate["translation_errors"][i] < 1e-12
    chosen = result["rotation_error_deg_mean"] * result["translation_error_mean"]
    assert chosen == pytest.approx(best, rel=1e-9)
    assert (result["translation_errors"] < 1e-12).any()  # the anchor camera


def test_pose_errors_camera_count_requirements():
    reference = _random_viewmats(2, _generator(25))
    estimated = align_viewmats(reference, _random_sim3(_generator(26), scale=2.0))
    result = pose_errors(estimated, reference, alignment="pairwise")
    assert result["translation_errors"].max() < 1e-11 and result["rotation_errors_deg"].max() < 1e-9
    with pytest.raises(ValueError, match="procrustes"):
        pose_errors(estimated, reference, alignment="procrustes")
    with pytest.raises(ValueError, match="alignment must be"):
        pose_errors(estimated, reference, alignment="icp")
    with pytest.raises(ValueError, match="equal shape"):
        pose_errors(estimated[:1], reference)


# ----------------------------------------------------------------------------------------------- pose noise


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-9), (torch.float32, 2e-3)])
def test_perturb_fixed_angle_gives_exact_rotation_error(dtype, atol):
    reference = _random_viewmats(50, _generator(27)).to(dtype)
    noisy = perturb_viewmats(reference, rot_std_deg=0.0, trans_std=0.0, seed=7, rot_fixed_deg=15.0)
    assert noisy.dtype == dtype
    result = pose_errors(noisy, reference, alignment="none")
    torch.testing.assert_close(
        result["rotation_errors_deg"], torch.full((50,), 15.0, dtype=dtype), rtol=0, atol=atol
    )
    assert result["translation_errors"].max() < 100 * torch.finfo(dtype).eps * 10  # centres stay put
    torch.testing.assert_close(noisy[:, 3], reference[:, 3], rtol=0, atol=0)


def test_perturb_rotation_rms_matches_sigma():
    # The geodesic error of a camera is |angle| with angle ~ N(0, sigma^2): E[error^2] = sigma^2 and
    # mean(error^2) / sigma^2 ~ chi^2_n / n, so RMS / sigma has standard deviation ~ 1 / sqrt(2 n) = 0.005 for
    # n = 20000. The tolerance is 5 standard deviations.
    num_cameras, sigma = 20000, 10.0
    reference = torch.eye(4, dtype=F64).repeat(num_cameras, 1, 1)
    noisy = perturb_viewmats(reference, rot_std_deg=sigma, trans_std=0.0, seed=11)
    errors = pose_errors(noisy, reference, alignment="none")["rotation_errors_deg"]
    rms = errors.square().mean().sqrt().item()
    assert abs(rms / sigma - 1.0) < 5.0 / math.sqrt(2 * num_cameras)
    # Mean |angle| = sigma sqrt(2/pi); relative std of the sample mean is sqrt(pi/2 - 1)/sqrt(n) ~ 0.0053.
    mean_ratio = errors.mean().item() / (sigma * math.sqrt(2 / math.pi))
    assert abs(mean_ratio - 1.0) < 5.0 * math.sqrt(math.pi / 2 - 1) / math.sqrt(num_cameras)
    # Axes are uniform on the sphere: each component of the unit axis has mean 0 and variance 1/3.
    axes = so3_log(noisy[:, :3, :3])
    axes = axes / axes.norm(dim=-1, keepdim=True)
    assert axes.mean(dim=0).abs().max() < 5.0 * math.sqrt(1 / 3) / math.sqrt(num_cameras)


def test_perturb_translation_rms_matches_sigma():
    # Each of the 3 n centre offsets ~ N(0, sigma^2); RMS / sigma has standard deviation ~ 1 / sqrt(6 n).
    num_cameras, sigma = 20000, 0.3
    reference = _random_viewmats(num_cameras, _generator(28))
    noisy = perturb_viewmats(reference, rot_std_deg=0.0, trans_std=sigma, seed=12)
    offsets = camera_centers(noisy) - camera_centers(reference)
    rms = offsets.square().mean().sqrt().item()
    assert abs(rms / sigma - 1.0) < 5.0 / math.sqrt(6 * num_cameras)
    assert offsets.mean(dim=0).abs().max() < 5.0 * sigma / math.sqrt(num_cameras)
    result = pose_errors(noisy, reference, alignment="none")
    assert result["rotation_errors_deg"].max() < 1e-9  # rotation untouched
    torch.testing.assert_close(result["translation_errors"], offsets.norm(dim=-1), rtol=0, atol=1e-12)


def test_perturb_rotates_in_the_camera_frame_about_the_camera_centre():
    gen = _generator(29)
    first, second = _random_viewmats(6, gen), _random_viewmats(6, gen)
    noisy_first = perturb_viewmats(first, rot_std_deg=20.0, trans_std=0.0, seed=4)
    noisy_second = perturb_viewmats(second, rot_std_deg=20.0, trans_std=0.0, seed=4)
    # R' = R_noise @ R: the left factor R' R^T depends only on the seed, not on the camera's rotation.
    noise_first = noisy_first[:, :3, :3] @ first[:, :3, :3].transpose(-1, -2)
    noise_second = noisy_second[:, :3, :3] @ second[:, :3, :3].transpose(-1, -2)
    torch.testing.assert_close(noise_first, noise_second, rtol=0, atol=1e-13)
    torch.testing.assert_close(camera_centers(noisy_first), camera_centers(first), rtol=0, atol=1e-12)


def test_perturb_is_reproducible_and_leaves_global_rng_alone():
    reference = _random_viewmats(8, _generator(30))
    rng_state = torch.get_rng_state()
    one = perturb_viewmats(reference, rot_std_deg=5.0, trans_std=0.1, seed=123)
    again = perturb_viewmats(reference, rot_std_deg=5.0, trans_std=0.1, seed=123)
    other = perturb_viewmats(reference, rot_std_deg=5.0, trans_std=0.1, seed=124)
    assert torch.equal(torch.get_rng_state(), rng_state)
    assert torch.equal(one, again)
    assert not torch.allclose(one, other)
    # The centre noise for a seed does not depend on how the rotation angle is chosen.
    fixed = perturb_viewmats(reference, rot_std_deg=0.0, trans_std=0.1, seed=123, rot_fixed_deg=15.0)
    torch.testing.assert_close(camera_centers(fixed), camera_centers(one), rtol=0, atol=1e-12)
    # Zero noise is the identity.
    torch.testing.assert_close(perturb_viewmats(reference, 0.0, 0.0, seed=1), reference, rtol=0, atol=1e-12)


def test_perturb_rejects_bad_arguments():
    reference = _random_viewmats(2, _generator(31))
    with pytest.raises(ValueError, match="not both"):
        perturb_viewmats(reference, rot_std_deg=5.0, trans_std=0.0, seed=0, rot_fixed_deg=15.0)
    with pytest.raises(ValueError, match=">= 0"):
        perturb_viewmats(reference, rot_std_deg=-1.0, trans_std=0.0, seed=0)
    with pytest.raises(ValueError, match=r"\[C, 4, 4\]"):
        perturb_viewmats(reference[0], rot_std_deg=1.0, trans_std=0.0, seed=0)


# --------------------------------------------------------------------------------------------- camera paths
def test_interpolated_viewmats_walk_the_orbit_between_neighbouring_cameras():
    base = torch.eye(4, dtype=F64)
    base[2, 3] = 4.0
    orbit = turntable_viewmats(base[None], 16)
    shuffled = orbit[::2][torch.tensor([3, 0, 6, 1, 5, 2, 7, 4])]  # 8 cameras 45 degrees apart, out of order
    order = azimuth_order(shuffled)
    assert len(set(order.tolist())) == 8
    # Neighbours in azimuth order are 45 degrees apart (2 turntable steps of 16).
    angles = rotation_error_deg(shuffled[order, :3, :3], shuffled[order.roll(-1), :3, :3])
    torch.testing.assert_close(angles, torch.full((8,), 45.0, dtype=F64))
    ends = interpolated_viewmats(shuffled, torch.tensor([0, 5]), torch.tensor([0.0, 1.0], dtype=F64))
    torch.testing.assert_close(ends, shuffled[order[[0, 6]]], rtol=0, atol=1e-12)
    middles = interpolated_viewmats(shuffled, torch.arange(8), torch.full((8,), 0.5, dtype=F64))
    # Each midpoint is an odd turntable frame (the frames between the even ones), each found exactly once.
    distances = torch.cdist(middles[:, :3, :].flatten(1), orbit[1::2, :3, :].flatten(1))
    assert distances.min(dim=1).values.max().item() < 1e-9
    assert sorted(distances.argmin(dim=1).tolist()) == list(range(8))
    quarter = interpolated_viewmats(shuffled, torch.arange(8), torch.full((8,), 0.25, dtype=F64))
    torch.testing.assert_close(camera_centers(quarter).norm(dim=-1), torch.full((8,), 4.0, dtype=F64))
