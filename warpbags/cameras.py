"""Pinhole camera geometry: world-to-camera matrices, camera centres, projection of world points.

Conventions (binding; the renderer uses them): ``viewmats`` are world-to-camera ``[C, 4, 4]`` matrices with
OpenCV camera axes (x right, y down, z forward): ``x_cam = R @ x_world + t`` with ``R = viewmats[..., :3, :3]``,
``t = viewmats[..., :3, 3]``. Plain torch, float32 or float64, on whatever device the inputs live on.
"""

from __future__ import annotations

import torch

__all__ = ["camera_centers", "project_points", "viewmats_from_centers"]


def camera_centers(viewmats: torch.Tensor) -> torch.Tensor:
    """Camera centres in world coordinates, ``c = -R^T t``.

    Args:
        viewmats: ``[..., C, 4, 4]`` world-to-camera matrices.

    Returns:
        ``[..., C, 3]`` camera centres (the world points that map to the camera origin).
    """
    rotations = viewmats[..., :3, :3]
    translations = viewmats[..., :3, 3]
    return -(rotations.transpose(-1, -2) @ translations[..., None])[..., 0]


def project_points(viewmats: torch.Tensor, Ks: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of world points into every camera.

    Args:
        viewmats: [C, 4, 4] world-to-camera. Ks: [C, 3, 3]. points: [P, 3] world.

    Returns:
        (pixels [C, P, 2] in the image's continuous coordinates (pixel centres at +0.5), depths [C, P]). Points at
        or behind depth 1e-6 get finite but meaningless pixels: mask them by depth.
    """
    cam = points[None] @ viewmats[:, :3, :3].transpose(1, 2) + viewmats[:, None, :3, 3]  # [C, P, 3]
    depths = cam[..., 2]
    safe = torch.where(depths > 1e-6, depths, torch.ones_like(depths))
    u = Ks[:, None, 0, 0] * cam[..., 0] / safe + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / safe + Ks[:, None, 1, 2]
    return torch.stack([u, v], dim=-1), depths


def viewmats_from_centers(rotations: torch.Tensor, centers: torch.Tensor) -> torch.Tensor:
    """World-to-camera matrices of cameras with the given rotations and centres (the inverse of `camera_centers`).

    Args:
        rotations: ``[..., 3, 3]`` world-to-camera rotations.
        centers: ``[..., 3]`` camera centres in world coordinates.

    Returns:
        ``[..., 4, 4]`` world-to-camera matrices with ``t = -R c``.
    """
    translations = -(rotations @ centers[..., None])
    top = torch.cat([rotations, translations], dim=-1)
    bottom = torch.zeros(*rotations.shape[:-2], 1, 4, dtype=rotations.dtype, device=rotations.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)
