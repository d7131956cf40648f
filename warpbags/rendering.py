"""`rasterization()`: the one public rendering entry point, composed from the stages in `warpbags.wrapper`."""

from __future__ import annotations

import operator
from typing import Any

import torch

from warpbags.wrapper import (
    apply_pose_deltas,
    bin_gaussians,
    project_gaussians,
    rasterize_to_pixels,
    spherical_harmonics,
)

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")

# Tile edge in pixels. On CUDA 16 is standard; on CPU smaller tiles visit far fewer non-overlapping Gaussians
# (`python bench/rasterize.py --tile-size 4` against 16: forward + backward 1.6-2.3x faster at 4 px).
DEFAULT_TILE_SIZE = {"cuda": 16, "cpu": 4}


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    pose_deltas: torch.Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    render_mode: str = "RGB",
    tile_size: int | None = None,
    eps2d: float = 0.3,
    cpu_threads: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render N 3D Gaussians into C cameras, differentiably, with optional per-camera pose corrections.

    Same contract as gsplat's `rasterization` where they overlap. Gradients flow to means, quats, scales,
    opacities, colors, viewmats, Ks, backgrounds and pose_deltas.

    Args:
        means: [N, 3] Gaussian centres (world).
        quats: [N, 4] rotations as (w, x, y, z) quaternions; normalized internally.
        scales: [N, 3] linear scales (standard deviations along the Gaussian's axes).
        opacities: [N] in [0, 1].
        colors: [N, 3] or [C, N, 3] RGB, or [N, K, 3] spherical-harmonics coefficients when `sh_degree` is set
            (3DGS convention: colour = max(SH(dir) + 0.5, 0), dir from the camera centre to the Gaussian).
        viewmats: [C, 4, 4] world-to-camera matrices, OpenCV axes (x right, y down, z forward).
        Ks: [C, 3, 3] pinhole intrinsics; pixel centres are at (x + 0.5, y + 0.5).
        width, height: image size in pixels (0 gives an empty image).
        sh_degree: active SH degree (0-3), with (sh_degree + 1)^2 <= K; None means `colors` is RGB.
        backgrounds: [C, 3] colours composited behind the Gaussians (default black).
        pose_deltas: [C, 6] se(3) corrections [wx, wy, wz, vx, vy, vz] (rotation first), used as
            `exp(pose_deltas) @ viewmats`.
        near_plane, far_plane: camera-z culling range, 0 < near_plane < far_plane.
        render_mode: "RGB", "D" (alpha-weighted depth), "ED" (expected depth, D / alpha), "RGB+D" or "RGB+ED".
        tile_size: tile edge in pixels; default 16 on CUDA, 4 on CPU.
        eps2d: low-pass added to the 2D covariance (pixels^2, >= 0), as 3DGS.
        cpu_threads: host threads for CPU tensors, in every stage, forward and backward (None or 0, as the
            training config's `render_threads` 0: every usable core, or the limit of `threads.limited_host_threads`
            around the caller).

    Returns:
        render_colors: [C, H, W, D] with D = 3 (RGB), 1 (D, ED) or 4 (RGB+D, RGB+ED).
        render_alphas: [C, H, W, 1] accumulated opacity.
        meta: dict with the intermediate tensors: "viewmats" (pose-corrected), "means2d" [C, N, 2] (call
            `retain_grad()` on it for densification), "conics", "depths", "radii" [C, N], "colors" [C, N, 3], "bins"
            (tile intersections), "tile_size", "width", "height", "n_cameras".
    """
    width, height, sh_degree, tile_size, cpu_threads = _checked_scalars(width, height, sh_degree, tile_size,
                                                                        near_plane, far_plane, eps2d, cpu_threads)
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, backgrounds, pose_deltas, render_mode)
    if pose_deltas is not None:
        viewmats = apply_pose_deltas(viewmats, pose_deltas)
    if tile_size is None:
        tile_size = DEFAULT_TILE_SIZE["cuda" if means.is_cuda else "cpu"]

    means2d, conics, depths, radii = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d, cpu_threads
    )
    cams, n = depths.shape
    if sh_degree is not None:
        rgb = spherical_harmonics(means, colors, viewmats, sh_degree, cpu_threads)
    elif colors.dim() == 2:
        rgb = colors.unsqueeze(0).expand(cams, n, 3)
    else:
        rgb = colors

    bins = bin_gaussians(means2d, conics, opacities, radii, depths, width, height, tile_size, cpu_threads)
    image, depth, alpha = rasterize_to_pixels(means2d, conics, rgb, opacities, depths, bins, width, height, cpu_threads)

    alpha = alpha.unsqueeze(-1)
    if backgrounds is not None:
        # Through `alpha`, the background also reaches every Gaussian's alpha gradient.
        image = image + (1.0 - alpha) * backgrounds[:, None, None, :]
    depth = depth.unsqueeze(-1)
    if render_mode.endswith("ED"):
        depth = depth / alpha.clamp_min(1e-10)
    channels = {"RGB": [image], "D": [depth], "ED": [depth], "RGB+D": [image, depth], "RGB+ED": [image, depth]}
    render_colors = torch.cat(channels[render_mode], dim=-1)

    meta = dict(
        viewmats=viewmats, means2d=means2d, conics=conics, depths=depths, radii=radii, colors=rgb, bins=bins,
        tile_size=tile_size, width=width, height=height, n_cameras=cams,
    )
    return render_colors, alpha, meta


def _checked_scalars(width, height, sh_degree, tile_size, near_plane, far_plane, eps2d, cpu_threads):
    """The integer arguments as Python ints (numpy integers too: Warp takes no other integer type), after checking
    every scalar argument. Unchecked, a float or bool was a Warp type error once the projection had run, a negative
    size a torch error, and a negative near plane rendered the Gaussians behind the camera."""
    width = _integer_argument("width", width, 0)  # a zero-size image renders as an empty one, with zero gradients
    height = _integer_argument("height", height, 0)
    if sh_degree is not None:
        sh_degree = _integer_argument("sh_degree", sh_degree, 0, 3)
    if tile_size is not None:  # pixels
        tile_size = _integer_argument("tile_size", tile_size, 1)
    if cpu_threads is not None:  # 0 is the default, as in the stages' own wrappers
        cpu_threads = _integer_argument("cpu_threads", cpu_threads, 0) or None
    if not 0 < near_plane < far_plane:  # also refuses NaN
        raise ValueError(f"the planes must satisfy 0 < near_plane < far_plane, got near_plane={near_plane!r}, "
                         f"far_plane={far_plane!r}")
    if not eps2d >= 0:
        raise ValueError(f"eps2d must be >= 0 (pixels^2), got {eps2d!r}")
    return width, height, sh_degree, tile_size, cpu_threads


def _integer_argument(name: str, value, lowest: int, highest: int | None = None) -> int:
    """`value` as an int if it is an integer (by `operator.index`; not a bool, which Warp refuses as an int) from
    `lowest` to `highest`."""
    if not isinstance(value, bool):
        try:
            integer = operator.index(value)
        except TypeError:
            pass
        else:
            if lowest <= integer and (highest is None or integer <= highest):
                return integer
    allowed = f">= {lowest}" if highest is None else f"from {lowest} to {highest}"
    raise ValueError(f"{name} must be an int {allowed}, got {value!r}")


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, backgrounds, pose_deltas, render_mode):
    if means.dtype not in (torch.float32, torch.float64):  # first: the other tensors are checked against it
        raise ValueError(f"means must be float32 or float64, got {means.dtype}")
    if viewmats.dim() != 3 or tuple(viewmats.shape[1:]) != (4, 4):  # before the camera count is read from it
        raise ValueError(f"viewmats must have shape [C, 4, 4], got {list(viewmats.shape)}")
    n, cams = means.shape[0], viewmats.shape[0]
    if cams == 0:
        raise ValueError("viewmats must hold at least one camera, got [0, 4, 4]")
    expected = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "scales": (scales, (n, 3)),
        "opacities": (opacities, (n,)),
        "viewmats": (viewmats, (cams, 4, 4)),
        "Ks": (Ks, (cams, 3, 3)),
    }
    if backgrounds is not None:
        expected["backgrounds"] = (backgrounds, (cams, 3))
    if pose_deltas is not None:
        expected["pose_deltas"] = (pose_deltas, (cams, 6))
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(tensor.shape)}")
        if tensor.dtype != means.dtype or tensor.device != means.device:
            raise ValueError(f"{name} is {tensor.dtype} on {tensor.device}; expected {means.dtype} on {means.device}")
    if sh_degree is None:
        if tuple(colors.shape) not in ((n, 3), (cams, n, 3)):
            raise ValueError(f"colors must be [N, 3] or [C, N, 3] RGB (or set sh_degree), got {list(colors.shape)}")
    else:
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[2] != 3 or colors.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(f"colors must be [N, K>={(sh_degree + 1) ** 2}, 3] SH coefficients, got {list(colors.shape)}")
    if colors.dtype != means.dtype or colors.device != means.device:
        raise ValueError(f"colors is {colors.dtype} on {colors.device}; expected {means.dtype} on {means.device}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {', '.join(RENDER_MODES)}, got {render_mode!r}")
