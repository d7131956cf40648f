"""warpbags.data.noise: pose noise of the stated size, in the camera frame, reproducible (CPU, float64); depth maps
degraded like a monocular network's."""

from __future__ import annotations

import math

import pytest
import torch
from random_poses import F64, generator, random_viewmats

from warpbags.alignment import pose_errors
from warpbags.cameras import camera_centers
from warpbags.data.noise import monocular_like_depths, perturb_viewmats
from warpbags.lie import so3_log

# ----------------------------------------------------------------------------------------------- pose noise


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-9), (torch.float32, 2e-3)])
def test_perturb_fixed_angle_gives_exact_rotation_error(dtype, atol):
    reference = random_viewmats(50, generator(27)).to(dtype)
    noisy = perturb_viewmats(reference, rot_std_deg=0.0, trans_std=0.0, seed=7, rot_fixed_deg=15.0)
    assert noisy.dtype == dtype
    result = pose_errors(noisy, reference, alignment="none")
    torch.testing.assert_close(
        result["rotation_errors_deg"], torch.full((50,), 15.0, dtype=dtype), rtol=0, atol=atol
    )
    assert result["translation_errors"].max() < 100 * torch.finfo(dtype).eps * 10  # centres stay put
    torch.testing.assert_close(noisy[:, 3], reference[:, 3], rtol=0, atol=0)


def test_rot_noise_fixed_gives_every_training_camera_exactly_that_angle():
    from types import SimpleNamespace

    from warpbags.camera_setup import given_viewmats
    from warpbags.configs.train import load_preset

    scene = SimpleNamespace(viewmats=random_viewmats(12, generator(3)))
    fixed = given_viewmats(scene, load_preset("quick", rot_noise_deg=15.0, rot_noise_fixed=True, trans_noise=0.3))
    errors = pose_errors(fixed, scene.viewmats, alignment="none")["rotation_errors_deg"]
    torch.testing.assert_close(errors, torch.full((12,), 15.0, dtype=F64), rtol=0, atol=1e-9)
    normal = given_viewmats(scene, load_preset("quick", rot_noise_deg=15.0, trans_noise=0.3))
    assert pose_errors(normal, scene.viewmats, alignment="none")["rotation_errors_deg"].std() > 2.0
    # the same centre noise either way: the angles are drawn all the same
    torch.testing.assert_close(camera_centers(fixed), camera_centers(normal))


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
    reference = random_viewmats(num_cameras, generator(28))
    noisy = perturb_viewmats(reference, rot_std_deg=0.0, trans_std=sigma, seed=12)
    offsets = camera_centers(noisy) - camera_centers(reference)
    rms = offsets.square().mean().sqrt().item()
    assert abs(rms / sigma - 1.0) < 5.0 / math.sqrt(6 * num_cameras)
    assert offsets.mean(dim=0).abs().max() < 5.0 * sigma / math.sqrt(num_cameras)
    result = pose_errors(noisy, reference, alignment="none")
    assert result["rotation_errors_deg"].max() < 1e-9  # rotation untouched
    torch.testing.assert_close(result["translation_errors"], offsets.norm(dim=-1), rtol=0, atol=1e-12)


def test_perturb_rotates_in_the_camera_frame_about_the_camera_centre():
    gen = generator(29)
    first, second = random_viewmats(6, gen), random_viewmats(6, gen)
    noisy_first = perturb_viewmats(first, rot_std_deg=20.0, trans_std=0.0, seed=4)
    noisy_second = perturb_viewmats(second, rot_std_deg=20.0, trans_std=0.0, seed=4)
    # R' = R_noise @ R: the left factor R' R^T depends only on the seed, not on the camera's rotation.
    noise_first = noisy_first[:, :3, :3] @ first[:, :3, :3].transpose(-1, -2)
    noise_second = noisy_second[:, :3, :3] @ second[:, :3, :3].transpose(-1, -2)
    torch.testing.assert_close(noise_first, noise_second, rtol=0, atol=1e-13)
    torch.testing.assert_close(camera_centers(noisy_first), camera_centers(first), rtol=0, atol=1e-12)


def test_perturb_is_reproducible_and_leaves_global_rng_alone():
    reference = random_viewmats(8, generator(30))
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
    reference = random_viewmats(2, generator(31))
    with pytest.raises(ValueError, match="not both"):
        perturb_viewmats(reference, rot_std_deg=5.0, trans_std=0.0, seed=0, rot_fixed_deg=15.0)
    with pytest.raises(ValueError, match=">= 0"):
        perturb_viewmats(reference, rot_std_deg=-1.0, trans_std=0.0, seed=0)
    with pytest.raises(ValueError, match=r"\[C, 4, 4\]"):
        perturb_viewmats(reference[0], rot_std_deg=1.0, trans_std=0.0, seed=0)


# ----------------------------------------------------------------------------------------------- depth maps


def _dome_depths(views: int = 3, size: int = 48) -> torch.Tensor:
    """A hemisphere of radius 1 in front of a camera at distance 5, in `views` copies: depth 4 at its centre."""
    coords = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2.4 - 1.2
    y, x = torch.meshgrid(coords, coords, indexing="ij")
    height = (1 - x**2 - y**2).clamp_min(0).sqrt()
    return torch.where(x**2 + y**2 < 1, 5 - height, torch.zeros_like(height)).expand(views, size, size).clone()


def test_monocular_like_depths_keep_the_support_and_the_shape_roughly():
    exact = _dome_depths()
    degraded = monocular_like_depths(exact, seed=3)
    assert torch.equal(degraded > 0, exact > 0)  # the object's pixels, no more, no fewer
    torch.testing.assert_close(degraded, monocular_like_depths(exact, seed=3), rtol=0, atol=0)  # reproducible
    for view in range(exact.shape[0]):
        valid = exact[view] > 0
        a, b = 1 / exact[view][valid], 1 / degraded[view][valid]
        correlation = float(torch.corrcoef(torch.stack([a, b]))[0, 1])
        # relief kept (a network sees the shape), but neither exact nor an affine map of the truth
        assert 0.6 < correlation < 0.99, correlation
    assert not torch.equal(degraded[0], degraded[1])  # each view its own errors
