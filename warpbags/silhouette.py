"""Pose signals from object masks with a long reach: a closed-form start and silhouette losses (NeRS-style).

A per-pixel mask loss has no gradient where the rendered and true silhouettes do not overlap, and a camera 15
degrees off can miss the object entirely. These terms reach further:

- `centroid_start`: each camera is turned (about its own centre) so that the ray through its mask centroid passes
  through the point closest to all the centroid rays, the object centre. Closed form, no rendering; it fixes pan
  and tilt, not roll or distance.
- `SilhouetteTargets.distance_loss`: rendered alpha times the distance transform of the mask (NeRS's
  mean(alpha * DT)): alpha outside the mask is pushed towards it (or away) from any distance.
- `SilhouetteTargets.chamfer_loss`: a two-sided chamfer between projected object points (Gaussian centres) and the
  mask's edge pixels, in image sizes: points outside the mask are pulled in, and every edge pixel pulls the nearest
  point, so the projection comes to fill the silhouette. It needs no rasterization at all.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from warpbags.cameras import camera_centers, project_points
from warpbags.lie import so3_exp
from warpbags.wrapper import nearest_points

EDGE_POINTS = 300  # mask edge pixels per view for the chamfer (NeRS's count)


def nearest_distances(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """[Q] distance from each of [Q, 2] `queries` to its nearest of [P, 2] `points`, differentiable in both.

    The nearest point is found without a graph (`warpbags.wrapper.nearest_points`: a grid search, exact, ties to
    the lowest index; a k-d tree built per step took 14-18 ms of a 100k-Gaussian step on one thread), then the Q
    distances are taken directly: the gradient is min's, without the dense [Q, P] distance matrix whose backward
    dominated such a step, and exact where torch.cdist's matrix-product form loses a tenth of a pixel to
    cancellation.
    """
    return (queries - points[nearest_points(queries, points)]).norm(dim=-1)


def mask_centroids(masks: torch.Tensor) -> torch.Tensor:
    """[C, 2] pixel coordinates (pixel centres at +0.5) of each [C, H, W] mask's centre of mass."""
    cams, height, width = masks.shape
    ys = torch.arange(height, dtype=masks.dtype) + 0.5
    xs = torch.arange(width, dtype=masks.dtype) + 0.5
    mass = masks.sum(dim=(1, 2)).clamp_min(1e-12)
    return torch.stack([(masks.sum(1) * xs).sum(-1) / mass, (masks.sum(2) * ys).sum(-1) / mass], dim=-1)


def centroid_rays(masks: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit ray directions [C, 3] through the mask centroids, in camera and in world coordinates."""
    centroids = mask_centroids(masks).to(Ks)
    camera = torch.stack([(centroids[:, 0] - Ks[:, 0, 2]) / Ks[:, 0, 0], (centroids[:, 1] - Ks[:, 1, 2]) / Ks[:, 1, 1],
                          torch.ones_like(centroids[:, 0])], dim=-1)
    camera = camera / camera.norm(dim=-1, keepdim=True)
    world = (viewmats[:, :3, :3].transpose(1, 2) @ camera[..., None])[..., 0]
    return camera, world


def rays_meeting_point(origins: torch.Tensor, directions: torch.Tensor, min_spread: float = 0.0) -> torch.Tensor | None:
    """The least-squares point closest to the lines origins + s directions: x with sum_c P_c x = sum_c P_c o_c,
    P_c = I - d_c d_c^T. The one implementation for the mask-centroid start, the trainer's object centre and the
    scenes' normalization (`warpbags.data.loaders.object_center`).

    Computed in float64 with NumPy (LAPACK's solve): the normalization of the scenes was first computed so, and it
    is kept to the last digit.

    Args:
        origins: [C, 3] points on the lines. directions: [C, 3] unit directions, C >= 2.
        min_spread: return None when the smallest eigenvalue of sum_c P_c is below `min_spread` times the largest
            (nearly parallel lines, a forward-facing capture: the point is ill-determined along them); 0 never does.

    Returns:
        [3] the point, in the dtype and on the device of `origins`; or None (see `min_spread`).
    """
    lines = directions.detach().cpu().double().numpy()
    points = origins.detach().cpu().double().numpy()
    projectors = np.eye(3)[None] - lines[:, :, None] * lines[:, None, :]
    system = projectors.sum(0)
    if min_spread > 0:
        eigenvalues = np.linalg.eigvalsh(system)
        if eigenvalues[0] < min_spread * eigenvalues[-1]:
            return None
    point = np.linalg.solve(system, np.einsum("cij,cj->i", projectors, points))
    return torch.from_numpy(point).to(origins)


def _rotation_between(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """[C, 3, 3] the smallest rotations taking unit vectors source [C, 3] onto target [C, 3]."""
    axis = torch.linalg.cross(source, target)
    sin_angle = axis.norm(dim=-1, keepdim=True)
    cos_angle = (source * target).sum(-1, keepdim=True)
    angle = torch.atan2(sin_angle, cos_angle)
    return so3_exp(axis / sin_angle.clamp_min(1e-12) * angle)


def centroid_start(masks: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Turn every camera about its centre so that its mask-centroid ray passes through the object centre.

    Args:
        masks: [C, H, W] object masks in [0, 1]. viewmats: [C, 4, 4] world-to-camera. Ks: [C, 3, 3].

    Returns:
        (the turned [C, 4, 4] world-to-camera matrices, the [3] object centre they now agree on exactly).
    """
    viewmats = viewmats.double()
    ray_camera, ray_world = centroid_rays(masks.double(), viewmats, Ks.double())
    center = rays_meeting_point(camera_centers(viewmats), ray_world)
    to_center = (viewmats[:, :3, :3] @ center + viewmats[:, :3, 3])
    to_center = to_center / to_center.norm(dim=-1, keepdim=True)
    turn = torch.eye(4, dtype=torch.float64).repeat(len(viewmats), 1, 1)
    turn[:, :3, :3] = _rotation_between(to_center, ray_camera)
    return turn @ viewmats, center


class SilhouetteTargets:
    """Per-view distance transforms and edge pixels of the masks, for the long-range silhouette losses.

    Args:
        masks: [C, H, W] in [0, 1] (threshold 0.5).
    """

    def __init__(self, masks: torch.Tensor):
        self.height, self.width = masks.shape[1:]
        self.size = float(max(self.width, self.height))
        outside, edges = [], []
        for mask in (masks.detach().cpu().numpy() > 0.5).astype(np.uint8):
            # Distance (pixels) from each pixel outside the mask to the nearest mask pixel; 0 inside.
            outside.append(cv2.distanceTransform(1 - mask, cv2.DIST_L2, 5))
            contour = mask - cv2.erode(mask, np.ones((3, 3), np.uint8))
            ys, xs = np.nonzero(contour)
            pick = np.linspace(0, len(xs) - 1, min(EDGE_POINTS, len(xs))).astype(int) if len(xs) else []
            edges.append(torch.tensor(np.stack([xs[pick] + 0.5, ys[pick] + 0.5], -1) if len(xs) else np.zeros((0, 2)),
                                      dtype=torch.float32))
        self.outside_distance = torch.from_numpy(np.stack(outside)).float() / self.size  # [C, H, W], image sizes
        self.edges = edges  # per view [E, 2] pixel coordinates

    def to(self, device: torch.device) -> SilhouetteTargets:
        self.outside_distance = self.outside_distance.to(device)
        self.edges = [edge.to(device) for edge in self.edges]
        return self

    def distance_loss(self, alphas: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """NeRS's mean(alpha * DT(mask)) over [B, H, W] rendered alphas of views [B] (DT in image sizes).

        Rendering less (moving away, fading) lowers it too, and with no overlap that is most of its pose gradient:
        it must be paired with a term that wants the mask covered (the mask loss, the chamfer). Normalizing it by
        the rendered mass removes that, but made training diverge (synthetic, 15 deg: 0.9 -> 20 deg).
        """
        return (alphas * self.outside_distance[views].to(alphas)).mean()

    def chamfer_loss(self, points: torch.Tensor, weights: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                     views: torch.Tensor) -> torch.Tensor:
        """Two-sided chamfer between projected points and mask edges, in image sizes (NeRS's chamfer).

        Args:
            points: [P, 3] world points (e.g. Gaussian centres). weights: [P] their weights (e.g. opacities);
                points with weight <= 0.1 are left out of the edge-to-point side.
            viewmats: [B, 4, 4] the cameras of `views` (differentiable). Ks: [B, 3, 3]. views: [B] long.

        Returns:
            [] mean over views of: weighted mean DT at the projected points (point-to-mask) + mean distance from
            each edge pixel to its nearest projected point (mask-to-point).
        """
        pixels, depths = project_points(viewmats, Ks, points)
        in_front = (depths > 1e-3).to(points.dtype)
        grid = torch.stack([pixels[..., 0] / self.width * 2 - 1, pixels[..., 1] / self.height * 2 - 1], dim=-1)
        # Points beyond the image border get the border's distance plus their distance to it.
        inside_grid = grid.clamp(-1, 1)
        sampled = F.grid_sample(self.outside_distance[views][:, None].to(points.dtype), inside_grid[:, :, None],
                                mode="bilinear", align_corners=False)[:, 0, :, 0]
        beyond = ((grid - inside_grid) * torch.tensor([self.width, self.height], dtype=points.dtype,
                                                      device=points.device) / 2).norm(dim=-1) / self.size
        weight = weights[None] * in_front
        point_to_mask = ((sampled + beyond) * weight).sum(-1) / weight.sum(-1).clamp_min(1e-12)
        solid = (weights > 0.1)
        losses = []
        for b, view in enumerate(views.tolist()):
            edge = self.edges[view]
            projected = pixels[b][solid & (depths[b] > 1e-3)]
            if len(edge) == 0 or len(projected) == 0:
                losses.append(point_to_mask[b])
                continue
            nearest = nearest_distances(edge.to(projected), projected) / self.size
            losses.append(point_to_mask[b] + nearest.mean())
        return torch.stack(losses).mean()
