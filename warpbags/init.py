"""Initial Gaussians: the visual hull of the training masks (GaussianObject's voxel carving), or random points.

Carving under pose noise. A voxel is kept when it projects inside the mask in at least ``C - missed_views``
views (GaussianObject: ``N - 1``). With noisy poses the silhouettes no longer agree and the strict
intersection erodes the object (thin parts vanish first); two knobs make it tolerant, both in
`TrainConfig`: ``hull_dilation_px`` grows every mask before carving (a rotation error of ``a`` degrees moves
the silhouette by about ``f * tan(a)`` pixels, so a few pixels absorb small noise at low resolution), and
``hull_missed_views`` allows more views to disagree. Over-estimating the hull is cheap (densification prunes
transparent Gaussians; the mask loss pushes them out), under-estimating loses parts for good, so the quick
preset dilates. If carving leaves fewer than ``min_voxels`` voxels, points are drawn at random in the
region every camera sees (`random_points`; the note says when too little of it is seen by every camera).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from warpbags.cameras import project_points
from warpbags.kernels.sh import SH_C0  # colour = SH_C0 * sh0 + 0.5
from warpbags.wrapper import mean_neighbour_distances


def _project(points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int):
    """Pixel indices of points in every camera.

    Returns:
        rows, cols: [C, P] long pixel indices (clamped), in_image: [C, P] bool (in front and inside the image).
    """
    pixels, z = project_points(viewmats, Ks, points)
    u, v = pixels.unbind(-1)
    in_image = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    cols = u.floor().long().clamp(0, width - 1)
    rows = v.floor().long().clamp(0, height - 1)
    return rows, cols, in_image


def _carve(
    lower: torch.Tensor, upper: torch.Tensor, resolution: int, masks: torch.Tensor, viewmats: torch.Tensor,
    Ks: torch.Tensor, missed_views: int,
) -> tuple[torch.Tensor, float]:
    """Centres [V,3] of the voxels of a grid over the box [lower, upper] kept by the vote, and the voxel edge."""
    num_cameras, height, width = masks.shape
    steps = [torch.linspace(0.0, 1.0, resolution + 1, dtype=torch.float64)[:-1] + 0.5 / resolution] * 3
    grid = torch.stack(torch.meshgrid(*steps, indexing="ij"), -1).reshape(-1, 3)
    centers = (lower + grid * (upper - lower)).float()
    votes = torch.zeros(len(centers), dtype=torch.int32)
    for start in range(0, len(centers), 262144):
        chunk = centers[start : start + 262144]
        rows, cols, in_image = _project(chunk, viewmats, Ks, width, height)
        inside = masks[torch.arange(num_cameras)[:, None], rows, cols] > 0.5
        votes[start : start + len(chunk)] = (inside & in_image).sum(0).int()
    keep = votes >= num_cameras - missed_views
    voxel = float((upper - lower).max()) / resolution
    return centers[keep], voxel


def visual_hull(
    masks: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    *,
    resolution: int = 64,
    dilation_px: int = 0,
    missed_views: int = 1,
    bound: float = 2.5,
) -> tuple[torch.Tensor, float]:
    """Voxel-carved visual hull in two passes (coarse grid over a cube, then a finer one over the hull's box).

    Args:
        masks: [C, H, W] object masks in {0, 1}.
        viewmats: [C, 4, 4] world-to-camera (possibly noisy).
        Ks: [C, 3, 3] intrinsics at the mask resolution.
        resolution: voxels per axis of the second (fine) pass; the first uses 1.5x that over the cube.
        dilation_px: masks are dilated by this many pixels first.
        missed_views: a voxel may be outside the mask in this many views, but is always inside at least two
            (with 2 views, both): a single view's silhouette is a cone to the cube's walls.
        bound: half edge of the first pass's cube around the origin (normalized scenes: orbit radius 4).

    Returns:
        centres [V, 3] of the kept voxels (V may be 0) and the fine voxel edge length.
    """
    masks = masks.detach().float().cpu()
    if dilation_px > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilation_px + 1, 2 * dilation_px + 1))
        masks = torch.from_numpy(np.stack([cv2.dilate(m.numpy(), kernel) for m in masks]))
    viewmats, Ks = viewmats.detach().float().cpu(), Ks.detach().float().cpu()
    missed_views = min(missed_views, max(len(masks) - 2, 0))  # one view's silhouette holds no depth: two must agree
    lower = torch.full((3,), -bound, dtype=torch.float64)
    coarse, voxel = _carve(lower, -lower, int(resolution * 1.5), masks, viewmats, Ks, missed_views)
    if len(coarse) == 0:
        return coarse, voxel
    low, high = coarse.min(0).values.double() - voxel, coarse.max(0).values.double() + voxel
    center, half = 0.5 * (low + high), 0.5 * (high - low).max()
    return _carve(center - half, center + half, resolution, masks, viewmats, Ks, missed_views)


def point_colors(points: torch.Tensor, images: torch.Tensor, masks: torch.Tensor, viewmats: torch.Tensor,
                 Ks: torch.Tensor) -> torch.Tensor:
    """Mean colour [P, 3] of each point over the views in which it projects inside the mask (0.5 grey if none)."""
    num_cameras, height, width, _ = images.shape
    rows, cols, in_image = _project(points, viewmats.float().cpu(), Ks.float().cpu(), width, height)
    camera = torch.arange(num_cameras)[:, None]
    seen = (in_image & (masks.cpu()[camera, rows, cols] > 0.5)).float()  # [C,P]
    colors = images.cpu()[camera, rows, cols]  # [C,P,3]
    total = (colors * seen[..., None]).sum(0)
    count = seen.sum(0)[:, None]
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, 0.5))


def random_points(count: int, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                  generator: torch.Generator, bound: float = 1.5) -> tuple[torch.Tensor, int]:
    """Points uniform in the cube [-bound, bound]^3, kept only where every camera sees them, if enough are.

    Returns:
        [count, 3] points, and how many of the 8 x `count` drawn points every camera sees: when fewer than
        `count`, the points come from the whole cube instead.
    """
    points = (torch.rand(count * 8, 3, generator=generator) * 2 - 1) * bound
    _, _, in_image = _project(points, viewmats.float().cpu(), Ks.float().cpu(), width, height)
    seen = points[in_image.all(0)]
    return (seen if len(seen) >= count else points)[:count], len(seen)


def _initial_scales(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[P] initial scale of a Gaussian at each point: the mean distance to its k nearest other points, at least 1e-7
    (a grid search in Warp, `warpbags.wrapper.mean_neighbour_distances`). 3DGS (distCUDA2) and gsplat take the root
    of the mean squared distance to the 3 nearest instead, never smaller: kept as it is, as every result was trained
    from it."""
    if len(points) <= 1:
        return torch.full((len(points),), 0.01)
    return mean_neighbour_distances(points, min(k, len(points) - 1)).clamp_min(1e-7)


def initial_gaussians(
    points: torch.Tensor, colors: torch.Tensor, sh_degree: int, opacity: float = 0.1
) -> dict[str, torch.Tensor]:
    """Raw Gaussian parameters (3DGS parameterization) at the given points.

    Args:
        points: [N, 3] centres. colors: [N, 3] RGB in [0, 1]. sh_degree: maximum SH degree (0-3).
        opacity: initial opacity (3DGS: 0.1).

    Returns:
        dict with "means" [N,3], "scales" [N,3] (log), "quats" [N,4] (identity, wxyz), "opacities" [N] (logit),
        "sh0" [N,1,3], and "shN" [N,K-1,3] zeros when sh_degree > 0.
    """
    count = len(points)
    scales = torch.log(_initial_scales(points))[:, None].repeat(1, 3)
    quats = torch.zeros(count, 4)
    quats[:, 0] = 1.0
    params = {
        "means": points.float().clone(),
        "scales": scales,
        "quats": quats,
        "opacities": torch.full((count,), math.log(opacity / (1 - opacity))),
        "sh0": ((colors.float() - 0.5) / SH_C0)[:, None, :],
    }
    if sh_degree > 0:
        params["shN"] = torch.zeros(count, (sh_degree + 1) ** 2 - 1, 3)
    return params


def hull_or_random_points(
    images: torch.Tensor, masks: torch.Tensor | None, viewmats: torch.Tensor, Ks: torch.Tensor, *, method: str,
    count: int, resolution: int, dilation_px: int, missed_views: int, generator: torch.Generator, min_voxels: int = 100,
    sfm_points: torch.Tensor | None = None, sfm_colors: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, str]:
    """Initial points [N,3] and colours [N,3], and a one-line note on how they were made.

    method: "hull" (visual hull from the masks; random points when there are no masks or the hull is nearly
    empty), "sfm" (the scene's SfM points, subsampled to `count`; random points when it has none) or "random".
    """
    if method == "sfm":
        if sfm_points is not None and len(sfm_points) > 0:
            pick = torch.randperm(len(sfm_points), generator=generator)[:count]
            return sfm_points[pick].float(), sfm_colors[pick].float(), f"SfM points: {len(pick)} of {len(sfm_points)}"
        method = "random-fallback"
    num_cameras, height, width, _ = images.shape
    if method == "hull" and masks is not None:
        voxels, voxel = visual_hull(masks, viewmats, Ks, resolution=resolution, dilation_px=dilation_px,
                                    missed_views=missed_views)
        if len(voxels) >= min_voxels:
            pick = torch.randperm(len(voxels), generator=generator)[:count]
            jitter = (torch.rand(len(pick), 3, generator=generator) - 0.5) * voxel
            points = voxels[pick] + jitter
            colors = point_colors(points, images, masks, viewmats, Ks)
            return points, colors, f"visual hull: {len(voxels)} voxels, {len(points)} points"
        note = f"visual hull had only {len(voxels)} voxels; random points instead"
    else:
        note = {"random": "random points", "random-fallback": "no SfM points: random points"}.get(
            method, "no masks: random points")
    points, drawn_points_seen_by_all = random_points(count, viewmats, Ks, width, height, generator)
    colors = torch.rand(len(points), 3, generator=generator)
    note = f"{note} ({len(points)})"
    if drawn_points_seen_by_all < count:
        note += (f"; only {drawn_points_seen_by_all} of {8 * count} drawn points are seen by every camera, so they "
                 "come from the whole cube")
    return points, colors, note
