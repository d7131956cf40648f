"""Injected noise for benchmarks: perturbed copies of world-to-camera poses (the true ones stay put), and exact depth
maps degraded to what a monocular depth network gives (relative, smooth shape errors, soft edges)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from warpbags.cameras import camera_centers, viewmats_from_centers
from warpbags.data.scene import Scene
from warpbags.lie import so3_exp
from warpbags.blur import gaussian_blur

__all__ = ["PoseNoise", "monocular_like_depths", "noisy_viewmats", "perturb_viewmats"]


@dataclass(frozen=True)
class PoseNoise:
    """Per-camera pose noise in normalized scene units (camera orbit radius `ORBIT_RADIUS`).

    Attributes:
        rot_std_deg: rotation angle ~ N(0, rot_std_deg^2) degrees about a uniformly random axis (--rot-noise-deg).
        trans_std: camera-centre offset ~ N(0, trans_std^2 I) (--trans-noise).
        seed: seeds the draw.
        rot_fixed_deg: instead of rot_std_deg, rotate every camera by exactly this angle (random axis;
            --rot-noise-fixed).
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
      from ``N(0, rot_std_deg^2)`` degrees, or is exactly ``rot_fixed_deg`` (``--rot-noise-fixed``). The
      geodesic error of camera ``i`` is then ``|angle|`` (for ``|angle| <= 180``).
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


def monocular_like_depths(depths: torch.Tensor, seed: int, shape_error: float = 0.2, blur_px: float = 1.0,
                          pixel_noise: float = 0.02) -> torch.Tensor:
    """Exact depth maps made into what a monocular depth network gives, reproducibly from ``seed``.

    A synthetic scene renders exact depth; GaussianObject's captures come with ZoeDepth maps, and a capture without
    depth maps gets none at all. This is a model of the middle case, not a measurement of any network. Per view, in
    disparity (1 / depth) over the valid pixels (depth > 0):

    * a smooth shape error: a random field (a 4 x 4 grid of N(0, 1) values, bicubically upsampled) times
      ``shape_error`` times the view's disparity range, so the object's depth profile is off by about that share of
      its own relief, at low frequency;
    * soft edges: a normalized Gaussian blur of ``blur_px`` pixels within the valid pixels;
    * per-pixel noise: N(0, ``pixel_noise``^2) relative;
    * unknown scale and shift: disparity times U(0.5, 2) plus U(0, 1) times its median (the loss is invariant to
      both, as it must be for a network's relative output).

    Args:
        depths: [C, H, W] exact depths, 0 = no value.
        seed: seeds a local generator (the global RNG is untouched).

    Returns:
        [C, H, W] degraded depths, 0 where the input is 0, and where the shape error takes the disparity to 0 or
        below (the far end of a deep view: under 1% of its pixels).
    """
    generator = torch.Generator().manual_seed(seed)
    valid = depths > 0
    out = torch.zeros_like(depths)
    height, width = depths.shape[1:]
    for view in range(depths.shape[0]):
        mask = valid[view]
        if not mask.any():
            continue
        disparity = torch.where(mask, 1.0 / depths[view].clamp_min(1e-12), torch.zeros_like(depths[view]))
        values = disparity[mask]
        relief = float(values.max() - values.min())
        field = F.interpolate(torch.randn(1, 1, 4, 4, generator=generator, dtype=torch.float64), size=(height, width),
                              mode="bicubic", align_corners=True)[0, 0].to(depths)
        disparity = disparity + shape_error * relief * field
        # normalized blur: the valid pixels' weighted mean, so the background's zeros do not bleed in
        blurred = gaussian_blur(torch.stack([disparity * mask, mask.to(depths)], dim=-1)[None], blur_px)[0]
        disparity = blurred[..., 0] / blurred[..., 1].clamp_min(1e-12)
        disparity = disparity * (1 + pixel_noise * torch.randn(height, width, generator=generator,
                                                                dtype=torch.float64).to(depths))
        scale = 0.5 + 1.5 * float(torch.rand(1, generator=generator, dtype=torch.float64))
        shift = float(torch.rand(1, generator=generator, dtype=torch.float64)) * float(values.median())
        disparity = scale * disparity + shift
        out[view] = torch.where(mask & (disparity > 0), 1.0 / disparity.clamp_min(1e-12), torch.zeros_like(disparity))
    return out
