"""Pose noise: perturbed copies of world-to-camera poses (the true ones stay put), for a scene or any poses."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpbags.cameras import camera_centers, viewmats_from_centers
from warpbags.data.scene import Scene
from warpbags.lie import so3_exp

__all__ = ["PoseNoise", "noisy_viewmats", "perturb_viewmats"]


@dataclass(frozen=True)
class PoseNoise:
    """Per-camera pose noise in normalized scene units (camera orbit radius `ORBIT_RADIUS`).

    Attributes:
        rot_std_deg: rotation angle ~ N(0, rot_std_deg^2) degrees about a uniformly random axis (--rot-noise-deg).
        trans_std: camera-centre offset ~ N(0, trans_std^2 I) (--trans-noise).
        seed: seeds the draw.
        rot_fixed_deg: instead of rot_std_deg, rotate every camera by exactly this angle (random axis).
    """

    rot_std_deg: float = 0.0
    trans_std: float = 0.0
    seed: int = 0
    rot_fixed_deg: float | None = None


def noisy_viewmats(scene: Scene, noise: PoseNoise) -> torch.Tensor:
    """[C,4,4] perturbed world-to-camera poses in the scene's normalized world (`scene.viewmats` stays the truth).

    Both are in the same normalized frame, so `scene.normalization.invert_viewmats` exports either.
    """
    return perturb_viewmats(scene.viewmats, noise.rot_std_deg, noise.trans_std, noise.seed, noise.rot_fixed_deg)


def perturb_viewmats(
    viewmats: torch.Tensor,
    rot_std_deg: float,
    trans_std: float,
    seed: int,
    rot_fixed_deg: float | None = None,
) -> torch.Tensor:
    """Noisy copies of world-to-camera poses, reproducibly from ``seed``.

    Per camera ``i`` (world-to-camera rotation ``R_i``, centre ``c_i``):

    * rotation: ``R_i' = R_noise @ R_i`` with ``R_noise = so3_exp(angle * axis)``, i.e. a rotation in the
      camera frame about the camera's own centre. ``axis`` is uniform on the unit sphere; ``angle`` is drawn
      from ``N(0, rot_std_deg^2)`` degrees, or is exactly ``rot_fixed_deg`` (the BAGS report's fixed-15-degree
      experiment). The geodesic error of camera ``i`` is then ``|angle|`` (for ``|angle| <= 180``).
    * centre: ``c_i' = c_i + n_i`` with ``n_i ~ N(0, trans_std^2 I_3)`` in world units; ``t_i' = -R_i' c_i'``.

    Randomness comes from a local CPU ``torch.Generator`` seeded with ``seed`` (the global RNG state is left
    untouched); draws are made in float64 in the fixed order axes ``[C, 3]``, angles ``[C]``, centre offsets
    ``[C, 3]`` (angles are drawn even when ``rot_fixed_deg`` is given, so the centre noise for a seed does not
    depend on it), then cast to the input's dtype and device. The result is therefore the same on every
    device for a given seed and number of cameras.

    Args:
        viewmats: ``[C, 4, 4]`` world-to-camera matrices (rigid).
        rot_std_deg: standard deviation of the rotation angle, degrees, >= 0. Must be 0 when
            ``rot_fixed_deg`` is given.
        trans_std: standard deviation of each camera-centre coordinate, world units, >= 0.
        seed: seed of the local generator.
        rot_fixed_deg: if given, every camera is rotated by exactly this angle (degrees) about a random axis.

    Returns:
        ``[C, 4, 4]`` perturbed world-to-camera matrices, same dtype and device as ``viewmats``.

    Raises:
        ValueError: negative standard deviations, both ``rot_std_deg`` and ``rot_fixed_deg`` given, or
            ``viewmats`` not of shape ``[C, 4, 4]``.
    """
    if viewmats.ndim != 3 or viewmats.shape[-2:] != (4, 4):
        raise ValueError(f"viewmats must have shape [C, 4, 4], got {list(viewmats.shape)}")
    if rot_std_deg < 0 or trans_std < 0:
        raise ValueError(
            f"noise standard deviations must be >= 0, got rot_std_deg={rot_std_deg}, trans_std={trans_std}"
        )
    if rot_fixed_deg is not None and rot_std_deg != 0:
        raise ValueError(
            f"give either rot_std_deg ({rot_std_deg}) or rot_fixed_deg ({rot_fixed_deg}), not both; set rot_std_deg=0"
        )
    num_cameras = viewmats.shape[0]
    generator = torch.Generator(device="cpu").manual_seed(int(seed))
    draw = dict(generator=generator, dtype=torch.float64, device="cpu")
    axes = torch.randn(num_cameras, 3, **draw)
    axes = axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)
    angles_deg = torch.randn(num_cameras, **draw) * rot_std_deg
    if rot_fixed_deg is not None:
        angles_deg = torch.full_like(angles_deg, float(rot_fixed_deg))
    center_offsets = torch.randn(num_cameras, 3, **draw) * trans_std

    rotation_noise = so3_exp(axes * torch.deg2rad(angles_deg)[:, None]).to(viewmats)
    rotations = rotation_noise @ viewmats[:, :3, :3]
    centers = camera_centers(viewmats) + center_offsets.to(viewmats)
    return viewmats_from_centers(rotations, centers)
