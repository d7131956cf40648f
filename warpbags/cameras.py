"""Pinhole camera geometry: world-to-camera matrices, camera centres, projection of world points.

Conventions (binding; the renderer uses them): ``viewmats`` are world-to-camera ``[C, 4, 4]`` matrices with
OpenCV camera axes (x right, y down, z forward): ``x_cam = R @ x_world + t`` with ``R = viewmats[..., :3, :3]``,
``t = viewmats[..., :3, 3]``. Plain torch, float32 or float64, on whatever device the inputs live on.
"""

from __future__ import annotations

import torch

from warpbags.kernels.coherence import MIN_DEPTH  # points at or behind it have no image: one threshold, host and kernel
from warpbags.lie import rotation_between

__all__ = ["camera_centers", "improper_viewmats", "mean_viewmats", "moved_keeping_target", "pixel_directions",
           "project_points", "viewmats_from_centers"]

# How far a world-to-camera matrix read from a file may be from a rotation and a translation over [0, 0, 0, 1]
# (|R R^T - I|, |det R - 1|, the last row): loose, for float32 files (orthonormal to ~1e-6); a scaled, sheared,
# mirrored or damaged matrix is off by far more.
POSE_TOLERANCE = 1e-2


def improper_viewmats(viewmats: torch.Tensor, tolerance: float = POSE_TOLERANCE) -> torch.Tensor:
    """Indices of the ``[C, 4, 4]`` matrices that are not world-to-camera poses: not finite, or not a rotation
    (det +1) and a translation over the row ``[0, 0, 0, 1]`` within `tolerance`. The renderer takes them as such,
    so a scaled or mirrored one would be rendered as a wrong camera, not refused."""
    viewmats = viewmats.double()
    finite = torch.isfinite(viewmats).all(dim=-1).all(dim=-1)
    safe = torch.where(finite[:, None, None], viewmats, torch.eye(4, dtype=viewmats.dtype, device=viewmats.device))
    rotations = safe[:, :3, :3]
    identity = torch.eye(3, dtype=viewmats.dtype, device=viewmats.device)
    orthogonality = (rotations @ rotations.transpose(-1, -2) - identity).abs().amax(dim=(-1, -2))
    determinant = torch.linalg.det(rotations)
    last_row = (safe[:, 3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=viewmats.dtype, device=viewmats.device)).abs()
    proper = finite & (orthogonality <= tolerance) & ((determinant - 1).abs() <= tolerance) & (
        last_row.amax(dim=-1) <= tolerance)
    return torch.nonzero(~proper).flatten()


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
        or behind `MIN_DEPTH` get finite but meaningless pixels: mask them by depth.
    """
    cam = points[None] @ viewmats[:, :3, :3].transpose(1, 2) + viewmats[:, None, :3, 3]  # [C, P, 3]
    depths = cam[..., 2]
    safe = torch.where(depths > MIN_DEPTH, depths, torch.ones_like(depths))
    u = Ks[:, None, 0, 0] * cam[..., 0] / safe + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / safe + Ks[:, None, 1, 2]
    return torch.stack([u, v], dim=-1), depths


def pixel_directions(pixels: torch.Tensor, Ks: torch.Tensor) -> torch.Tensor:
    """The camera-frame directions at unit depth ([..., 3], z = 1) through [..., 2] pixel positions (pixel centres at
    +0.5) of cameras [..., 3, 3] `Ks` (broadcast): what `project_points` maps back to those pixels."""
    x = (pixels[..., 0] - Ks[..., 0, 2]) / Ks[..., 0, 0]
    y = (pixels[..., 1] - Ks[..., 1, 2]) / Ks[..., 1, 1]
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


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


def mean_viewmats(rotation_sums: torch.Tensor, center_sums: torch.Tensor, count: int) -> torch.Tensor:
    """The mean pose of each camera over `count` estimates, from their sums: the rotation nearest (Frobenius) to
    the mean rotation matrix, the chordal L2 mean, and the mean centre.

    Args:
        rotation_sums: ``[..., 3, 3]`` sums of world-to-camera rotations. center_sums: ``[..., 3]`` sums of centres.

    Returns:
        ``[..., 4, 4]`` world-to-camera matrices.
    """
    u, _, vh = torch.linalg.svd(rotation_sums / count)
    flip = torch.ones_like(rotation_sums[..., 0])  # a reflection's last axis turned back: a proper rotation
    flip[..., 2] = torch.sign(torch.linalg.det(u @ vh))
    return viewmats_from_centers(u @ (flip[..., None] * vh), center_sums / count)


def moved_keeping_target(viewmats: torch.Tensor, centers: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cameras moved to new centres, each then turned about its new centre by the smallest rotation that puts
    `target` back on the ray it was seen along.

    This is the best any pose estimate can do with the camera centres it has: the orientation is exact up to the
    turn that the centre error forces on a camera that keeps looking at the object. Pose errors of these cameras
    are the part of a rotation error that comes from the centres alone.

    Args:
        viewmats: ``[C, 4, 4]`` world-to-camera matrices (e.g. the reference poses).
        centers: ``[C, 3]`` new camera centres (e.g. estimated ones, in the same world frame).
        target: ``[3]`` the world point the cameras keep (e.g. the object centre); in front of every camera.

    Returns:
        ``[C, 4, 4]`` world-to-camera matrices with centres ``centers``.
    """
    rotations = viewmats[..., :3, :3]
    seen = rotations @ target + viewmats[..., :3, 3]
    moved = rotations @ (target - centers)[..., None]
    seen, moved = seen / seen.norm(dim=-1, keepdim=True), moved[..., 0] / moved[..., 0].norm(dim=-1, keepdim=True)
    # both unit, never opposite for a target in front
    return viewmats_from_centers(rotation_between(moved, seen) @ rotations, centers)
