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
- `SilhouetteTargets.coherence_loss`: silhouette coherence, a property of the poses and masks alone: the ray
  through every mask pixel of one view must pass through the other views' silhouette cones somewhere, as it does
  at the true poses (the visual hull of all views then projects onto each mask). Each ray is charged the least,
  over points along it, of the summed distances outside the other masks, so it pulls from any distance.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from warpbags.cameras import camera_centers, pixel_directions, project_points
from warpbags.kernels.coherence import BEHIND_CAMERA_DISTANCE, MIN_DEPTH
from warpbags.lie import rotation_between
from warpbags.wrapper import least_outside_samples, nearest_points

EDGE_POINTS = 300  # mask edge pixels per view for the chamfer (NeRS's count)
COHERENCE_GRID = 64  # silhouette coherence: rays through mask pixels of a grid of about this many per image side
COHERENCE_SAMPLES = 96  # points per ray, spread over the object's depth range


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
    _, height, width = masks.shape
    ys = torch.arange(height, dtype=masks.dtype, device=masks.device) + 0.5
    xs = torch.arange(width, dtype=masks.dtype, device=masks.device) + 0.5
    mass = masks.sum(dim=(1, 2)).clamp_min(1e-12)
    return torch.stack([(masks.sum(1) * xs).sum(-1) / mass, (masks.sum(2) * ys).sum(-1) / mass], dim=-1)


def centroid_rays(masks: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit ray directions [C, 3] through the mask centroids, in camera and in world coordinates."""
    centroids = mask_centroids(masks).to(Ks)
    camera = pixel_directions(centroids, Ks)
    camera = camera / camera.norm(dim=-1, keepdim=True)
    world = (viewmats[:, :3, :3].transpose(1, 2) @ camera[..., None])[..., 0]
    return camera, world


NEARLY_PARALLEL = 1e-3
"""`rays_meeting_point`'s `min_spread` for an object centre: rays within about 2 deg of one another (a forward-facing
capture) do not meet at one."""


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


def centroid_start(masks: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Turn every camera about its centre so that its mask-centroid ray passes through the object centre.

    Args:
        masks: [C, H, W] object masks in [0, 1]. viewmats: [C, 4, 4] world-to-camera. Ks: [C, 3, 3].

    Returns:
        (the turned [C, 4, 4] world-to-camera matrices, the [3] object centre they now agree on exactly), or None
        where the rays are nearly parallel (`NEARLY_PARALLEL`: a forward-facing capture has no such centre).
    """
    viewmats = viewmats.double()
    ray_camera, ray_world = centroid_rays(masks.double(), viewmats, Ks.double())
    center = rays_meeting_point(camera_centers(viewmats), ray_world, min_spread=NEARLY_PARALLEL)
    if center is None:
        return None
    to_center = (viewmats[:, :3, :3] @ center + viewmats[:, :3, 3])
    to_center = to_center / to_center.norm(dim=-1, keepdim=True)
    turn = torch.eye(4, dtype=torch.float64, device=viewmats.device).repeat(len(viewmats), 1, 1)
    turn[:, :3, :3] = rotation_between(to_center, ray_camera)
    return turn @ viewmats, center


class SilhouetteTargets:
    """Per-view distance transforms and edge pixels of the masks, for the long-range silhouette losses.

    Args:
        masks: [C, H, W] in [0, 1] (threshold 0.5).
        continued_beyond_frame: the distance outside a mask is measured as if the mask went on beyond the image
            border where it meets it (each border pixel repeated outward, half an image size), not as if the object
            ended at the frame. A capture whose object the frame cuts is then coherent at its true poses; without it
            the frame counts as background, and the coherence solve moves the cameras until the object fits inside
            every frame.
    """

    def __init__(self, masks: torch.Tensor, continued_beyond_frame: bool = False):
        self.height, self.width = masks.shape[1:]
        self.size = float(max(self.width, self.height))
        self.margin = round(self.size / 2) if continued_beyond_frame else 0  # pixels of continued mask per side
        outside, edges, foreground = [], [], []
        for mask in (masks.detach().cpu().numpy() > 0.5).astype(np.uint8):
            # Distance (pixels) from each pixel outside the mask to the nearest mask pixel; 0 inside.
            padded = cv2.copyMakeBorder(mask, *[self.margin] * 4, cv2.BORDER_REPLICATE)
            outside.append(cv2.distanceTransform(1 - padded, cv2.DIST_L2, 5))
            contour = mask - cv2.erode(mask, np.ones((3, 3), np.uint8))
            ys, xs = np.nonzero(contour)
            pick = np.linspace(0, len(xs) - 1, min(EDGE_POINTS, len(xs))).astype(int) if len(xs) else []
            edges.append(torch.tensor(np.stack([xs[pick] + 0.5, ys[pick] + 0.5], -1) if len(xs) else np.zeros((0, 2)),
                                      dtype=torch.float32))
            step = max(1, round(self.size / COHERENCE_GRID))
            ys, xs = np.nonzero(mask[::step, ::step])
            foreground.append(torch.tensor(np.stack([xs * step + 0.5, ys * step + 0.5], -1), dtype=torch.float32))
        # [C, H + 2 margin, W + 2 margin], image sizes
        self.outside_distance = torch.from_numpy(np.stack(outside)).float() / self.size
        self.edges = edges  # per view [E, 2] pixel coordinates
        self.foreground = foreground  # per view [F, 2] pixel coordinates of mask pixels on a coarse grid

    def to(self, device: torch.device) -> SilhouetteTargets:
        self.outside_distance = self.outside_distance.to(device)
        self.edges = [edge.to(device) for edge in self.edges]
        self.foreground = [pixels.to(device) for pixels in self.foreground]
        return self

    def distance_loss(self, alphas: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """NeRS's mean(alpha * DT(mask)) over [B, H, W] rendered alphas of views [B] (DT in image sizes).

        Rendering less (moving away, fading) lowers it too, and with no overlap that is most of its pose gradient:
        it must be paired with a term that wants the mask covered (the mask loss, the chamfer). Normalizing it by
        the rendered mass removes that, but made training diverge (synthetic, 15 deg: 0.9 -> 20 deg).
        """
        m = self.margin  # masks continued beyond the frame: the frame's own pixels are the renders'
        return (alphas * self.outside_distance[views, m:m + self.height, m:m + self.width].to(alphas)).mean()

    def chamfer_loss(self, points: torch.Tensor, weights: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                     views: torch.Tensor) -> torch.Tensor:
        """Two-sided chamfer between projected points and mask edges, in image sizes. NeRS's chamfer is the
        edge-to-point side, on 300 edge pixels drawn at random each step; here they are a fixed subset, every k-th in
        raster order, which leans to one side of each row (a reviewer measured the optimum of a ball's image moved
        by about 0.4 px from every edge pixel's); the point-to-edge side is NeRS's distance term applied to the
        points.

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
        weight = weights[None] * in_front
        point_to_mask = (self._outside_mask(pixels, views) * weight).sum(-1) / weight.sum(-1).clamp_min(1e-12)
        # The cut-off is the opacity Gaussians start with (`init.initial_gaussians`, 0.1 in float32): at each round's
        # first step none passes and only the point-to-mask side acts, from the next step on those whose opacity
        # rose. A cut-off of 0.05 that keeps fresh ones measured no better (synthetic 15 / 0.3, seeds 0-2: 0.55 deg
        # against 0.49; 2026-12-07, fortieth session), so every run keeps this one.
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

    def object_radius(self, viewmats: torch.Tensor, Ks: torch.Tensor, center: torch.Tensor) -> float:
        """A radius about the [3] object `center` that holds the object: 1.5 times the largest half-extent of a
        mask's bounding box, turned into scene units at that camera's distance from the centre."""
        distances = (camera_centers(viewmats) - center).norm(dim=-1)
        radii = [0.0]
        for view, pixels in enumerate(self.foreground):
            if len(pixels):
                half_extent = float((pixels.max(0).values - pixels.min(0).values).max()) / 2
                radii.append(half_extent / float(Ks[view, 0, 0]) * float(distances[view]))
        return 1.5 * max(radii)

    def coherence_loss(self, viewmats: torch.Tensor, Ks: torch.Tensor, center: torch.Tensor,
                       radius: float) -> torch.Tensor:
        """Silhouette coherence of all C cameras: the mean, over views and their mask pixels, of how far the pixel's
        ray misses the other views' silhouette cones (image sizes; 0 where it passes through all of them).

        A ray is sampled at `COHERENCE_SAMPLES` depths within `radius` of the [3] object `center`; each point is
        charged the sum over the other views of its distance outside their masks (the distance transform; beyond
        the image border, plus the distance to it), and the ray the least of those. With exact masks it is 0 at
        the true poses (where the frame cuts the object, only with the masks continued beyond it). It is
        one-sided, so it fixes fewer degrees of freedom than a pose has (four views 90 deg apart leave a set of
        coherent poses a few degrees wide): a start for the photometric terms, not an answer.

        Args:
            viewmats: [C, 4, 4] world-to-camera of every view (differentiable). Ks: [C, 3, 3].
            center: [3] object centre. radius: the depth range's half-width about it (`object_radius`).
        """
        dtype, device = viewmats.dtype, viewmats.device
        Ks = Ks.to(dtype)
        views = [view for view in range(len(viewmats)) if len(self.foreground[view])] if len(viewmats) > 1 else []
        if not views:
            return viewmats.sum() * 0
        centers = camera_centers(viewmats)
        offsets = torch.linspace(-radius, radius, COHERENCE_SAMPLES, dtype=dtype, device=device)
        depths = (center.to(dtype) - centers).norm(dim=-1)[:, None] + offsets  # [C, S] along each optical axis
        rays = []  # per view [F, 3]: world directions at unit depth through its mask pixels
        for view in views:
            rays.append(pixel_directions(self.foreground[view].to(dtype), Ks[view]) @ viewmats[view, :3, :3])
        ray_views = torch.cat([torch.full((len(r),), view, device=device) for view, r in zip(views, rays)])
        # where along each ray the least is, searched without a graph (kernels/coherence.py): the min's gradient
        # reaches that point alone
        least = least_outside_samples(torch.cat(rays).detach(), ray_views, centers.detach(), depths.detach(),
                                      viewmats.detach(), Ks, self.outside_distance, self.margin, self.size)
        misses = []
        for view, view_rays, chosen in zip(views, rays, least.split([len(r) for r in rays])):
            # the samples' depths move with the camera centre, and so does the chosen one (the gradient of the min)
            points = centers[view] + view_rays * depths[view, chosen][:, None]
            misses.append(self._outside_other_views(points, view, viewmats, Ks).mean())
        return torch.stack(misses).mean()

    def _outside_other_views(self, points: torch.Tensor, view: int, viewmats: torch.Tensor,
                             Ks: torch.Tensor) -> torch.Tensor:
        """[N] the sum over every view but `view` of the distance of [N, 3] world points outside its mask, in image
        sizes (`_outside_mask`)."""
        others = [other for other in range(len(viewmats)) if other != view]
        projected, depths = project_points(viewmats[others], Ks[others], points)  # [C-1, N, 2], [C-1, N]
        outside = self._outside_mask(projected, torch.tensor(others, device=points.device))
        # outside the cone of a camera the point is behind, as the search charges it (kernels/coherence.py)
        return torch.where(depths > MIN_DEPTH, outside, BEHIND_CAMERA_DISTANCE).sum(0)

    def _outside_mask(self, pixels: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """[B, N] the distance (image sizes) of [B, N, 2] pixel positions outside the masks of views [B], bilinear in
        the distance transform; beyond the image border (or the continued masks' margin), the distance at the
        nearest point of the border plus the distance to it, so that a projection off the image is still pulled back.

        Border padding: between the outermost pixel centres and the image edge (and so at every clamped point) the
        distance is the outermost pixel's; zero padding would blend in a zero there (half of it at the edge)."""
        scale = torch.tensor([self.width + 2 * self.margin, self.height + 2 * self.margin], dtype=pixels.dtype,
                             device=pixels.device) / 2
        grid = (pixels + self.margin) / scale - 1
        inside_grid = grid.clamp(-1, 1)
        sampled = F.grid_sample(self.outside_distance[views][:, None].to(pixels.dtype), inside_grid[:, :, None],
                                mode="bilinear", padding_mode="border", align_corners=False)[:, 0, :, 0]
        beyond = ((grid - inside_grid) * scale).norm(dim=-1) / self.size
        return sampled + beyond
