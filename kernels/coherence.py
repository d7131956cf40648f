"""Silhouette coherence: where along each mask pixel's ray the ray comes nearest to passing through every other
view's silhouette (the search of `warpbags.silhouette.SilhouetteTargets.coherence_loss`).

A ray through a mask pixel of view v is sampled at S depths about the object centre; each sample is charged the sum,
over the other views, of its distance outside their masks (a bilinear read of the distance transform, plus the
distance beyond the image border); the ray keeps the sample with the least charge (the first of equal ones). The
samples are visited from the middle of the range outwards and a sample is dropped as soon as its partial sum exceeds
the least so far (every term is >= 0, and adding one never lowers a float sum), which changes no answer. The
loss then takes its gradient at that sample alone, in torch. One thread per ray walks its samples and the other
views without writing a point or a projection anywhere: the torch version materialized [F, S, 3] points and their
[C - 1, F, S, 2] projections, and spent 90% of the coherence solve there.

`outside_mask_distance` reads as `torch.nn.functional.grid_sample(..., mode="bilinear", padding_mode="border",
align_corners=False)` does, so the two agree to float rounding. Generic over float32/float64 in the geometry; the
distance transforms are float32.
"""

from typing import Any

import warp as wp

# A point at or behind this depth has no image in a camera: `warpbags.cameras.project_points` gives it finite,
# meaningless pixels (the host's projection and alignment read this threshold too). In a view, it lies outside the
# silhouette cone, which opens in front of the camera: it is charged BEHIND_CAMERA_DISTANCE (image sizes) for that
# view, as a pixel that far off the image would be (within 0.2 deg of 90 deg off the axis at fields of view above
# 16 deg, 0.7 deg at 5 deg). Projected with a stand-in depth, it could land inside the mask and be charged nothing
# (an L-BFGS trial step of the coherence solve, or a camera turned away from the object).
MIN_DEPTH = 1.0e-6
BEHIND_CAMERA_DISTANCE = 1.0e3


@wp.func
def outside_mask_distance(distances: wp.array3d(dtype=wp.float32), view: int, x: Any, y: Any, margin: Any, size: Any):
    """The distance (image sizes) of pixel position (x, y) (pixel centres at +0.5) outside view's mask: the
    distance transform (`distances`: [C, H + 2 margin, W + 2 margin], image sizes) read bilinearly, clamped to its
    border, plus the distance from (x, y) to the border where it lies beyond it."""
    zero = type(x)(0.0)
    half = type(x)(0.5)
    height = distances.shape[1]
    width = distances.shape[2]
    px = x + margin
    py = y + margin
    cx = wp.clamp(px, zero, type(x)(width))
    cy = wp.clamp(py, zero, type(x)(height))
    beyond = wp.sqrt((px - cx) * (px - cx) + (py - cy) * (py - cy)) / size
    sx = wp.clamp(cx - half, zero, type(x)(width - 1))
    sy = wp.clamp(cy - half, zero, type(x)(height - 1))
    x0 = int(wp.floor(sx))
    y0 = int(wp.floor(sy))
    x1 = wp.min(x0 + 1, width - 1)
    y1 = wp.min(y0 + 1, height - 1)
    wx = sx - type(x)(x0)
    wy = sy - type(x)(y0)
    one = type(x)(1.0)
    top = (one - wx) * type(x)(distances[view, y0, x0]) + wx * type(x)(distances[view, y0, x1])
    bottom = (one - wx) * type(x)(distances[view, y1, x0]) + wx * type(x)(distances[view, y1, x1])
    return (one - wy) * top + wy * bottom + beyond


@wp.kernel(enable_backward=False)
def least_outside_sample_kernel(rays: wp.array(dtype=Any), ray_views: wp.array(dtype=wp.int32),
                                origins: wp.array(dtype=Any), depths: wp.array2d(dtype=Any),
                                viewmats: wp.array(dtype=Any), intrinsics: wp.array(dtype=Any),
                                distances: wp.array3d(dtype=wp.float32), margin: Any, size: Any,
                                least: wp.array(dtype=wp.int32)):
    """For ray r (world direction at unit depth `rays[r]` from the centre `origins[v]` of its view v =
    `ray_views[r]`), the index of the sample of `depths[v]` whose summed distance outside the other views' masks
    is least. viewmats: [C] world-to-camera; intrinsics: [C] (fx, fy, cx, cy)."""
    r = wp.tid()
    view = ray_views[r]
    direction = rays[r]
    origin = origins[view]
    samples = depths.shape[1]
    zero = type(margin)(0.0)
    best = zero  # read only once best_sample >= 0
    best_sample = int(-1)
    for step in range(samples):
        # from the middle of the depth range outwards, where the object is: a low total found early prunes the rest.
        # Steps 0, 1, 2, ... visit S/2, S/2 - 1, S/2 + 1, ... down to 0 and up to S - 1, each sample once: s needs
        # no bounds check
        s = samples / 2 + (step + 1) / 2
        if step % 2 == 1:
            s = samples / 2 - (step + 1) / 2
        point = origin + direction * depths[view, s]
        total = zero
        pruned = int(0)
        for other in range(viewmats.shape[0]):
            # the terms are >= 0, so a partial sum above the best can only end above it: stop there
            if other != view and pruned == 0:
                camera = wp.transform_point(viewmats[other], point)
                z = camera[2]
                if z <= type(z)(MIN_DEPTH):
                    total = total + type(z)(BEHIND_CAMERA_DISTANCE)
                else:
                    k = intrinsics[other]
                    u = k[0] * camera[0] / z + k[2]
                    v = k[1] * camera[1] / z + k[3]
                    total = total + outside_mask_distance(distances, other, u, v, margin, size)
                if best_sample >= 0 and total > best:
                    pruned = 1
        if pruned == 0 and (best_sample < 0 or total < best or (total == best and s < best_sample)):
            best = total
            best_sample = s
    least[r] = best_sample
