"""Rasterization: front-to-back alpha compositing per pixel over its tile's depth-sorted Gaussians.

Forward, per pixel:  alpha_i = min(0.99, opacity_i * exp(-sigma_i)),  sigma_i = 1/2 d^T conic_i d,
    C = sum_i c_i alpha_i T_i,  D = sum_i z_i alpha_i T_i,  T_i = prod_{j<i} (1 - alpha_j),  A = 1 - T_final.
Contributions with alpha < 1/255 are skipped, and compositing stops before a Gaussian that would bring the
transmittance to 1e-4 or below (gsplat's rule). The forward saves T_final and the end of the contributing range.

The backward is written by hand and walks the same list back to front, recovering T_i = T_{i+1} / (1 - alpha_i):
Warp's automatic adjoint of this dynamic loop is silently wrong (dynamic loops are not replayed), so neither
kernel is differentiated by Warp.

Pixels are visited tile-major (all pixels of a tile, then the next tile) so a launch over a range of tiles touches
one Gaussian list at a time; `first_pixel` offsets the launch so host threads can take disjoint tile ranges.
Gradient buffers are written with atomic adds: on CUDA one buffer, on CPU one private buffer per host thread
(CPU atomics are plain adds).
"""

from typing import Any

import warp as wp

ALPHA_THRESHOLD = 1.0 / 255.0
SIGMA_CUTOFF = 5.545177444479562  # ln(255)
MAX_ALPHA = 0.99
TRANSMITTANCE_MIN = 1.0e-4


@wp.func
def locate_pixel(index: int, width: int, height: int, tile_size: int, tiles_x: int, tiles_y: int):
    """Tile-major pixel index -> (camera, global tile, x, y, flat output index or -1 outside the image)."""
    pixels_per_tile = tile_size * tile_size
    tiles_per_cam = tiles_x * tiles_y
    tile = index / pixels_per_tile
    local = index - tile * pixels_per_tile
    cam = tile / tiles_per_cam
    tile_in_cam = tile - cam * tiles_per_cam
    ty = tile_in_cam / tiles_x
    tx = tile_in_cam - ty * tiles_x
    x = tx * tile_size + local % tile_size
    y = ty * tile_size + local / tile_size
    out = -1
    if x < width and y < height:
        out = (cam * height + y) * width + x
    return cam, tile, x, y, out


@wp.func
def gaussian_falloff(mean2d: Any, conic: Any, px: Any, py: Any):
    """sigma = 1/2 d^T conic d with d = pixel centre - mean; also returns d."""
    dx = px - mean2d[0]
    dy = py - mean2d[1]
    half = type(dx)(0.5)
    sigma = half * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
    return sigma, dx, dy


@wp.func
def out_of_reach(sigma: Any):
    """True where no opacity can make the Gaussian count: sigma < 0 (a numerically indefinite conic) or
    sigma > ln(255), where even opacity 1 gives alpha < 1/255. Most visits of a tile's list end here, before
    the opacity is read or the exponential computed."""
    return sigma < type(sigma)(0.0) or sigma > type(sigma)(SIGMA_CUTOFF)


@wp.func
def splat_alpha(opacity: Any, sigma: Any):
    """(alpha, exp(-sigma)) with alpha = min(0.99, opacity exp(-sigma)), or alpha = 0 below the 1/255 cut-off."""
    zero = type(sigma)(0.0)
    falloff = wp.exp(-sigma)
    alpha = wp.min(type(sigma)(MAX_ALPHA), opacity * falloff)
    if alpha < type(sigma)(ALPHA_THRESHOLD):
        alpha = zero
    return alpha, falloff


@wp.kernel(enable_backward=False)
def rasterize_forward_kernel(
    means2d: wp.array(dtype=Any),
    conics: wp.array(dtype=Any),
    colors: wp.array(dtype=Any),
    opacities: wp.array(dtype=Any),
    depths: wp.array(dtype=Any),
    tile_offsets: wp.array(dtype=wp.int32),
    isect_ids: wp.array(dtype=wp.int32),
    num_gaussians: int,
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    first_pixel: int,
    out_colors: wp.array(dtype=Any),
    out_depths: wp.array(dtype=Any),
    out_alphas: wp.array(dtype=Any),
    final_transmittance: wp.array(dtype=Any),
    isect_end: wp.array(dtype=wp.int32),
):
    cam, tile, x, y, pix = locate_pixel(first_pixel + wp.tid(), width, height, tile_size, tiles_x, tiles_y)
    if pix < 0:
        return
    # isect ids are flat (camera, Gaussian) indices and opacities per Gaussian: one subtraction per visit instead
    # of an integer division
    first_gaussian = cam * num_gaussians
    px = out_depths.dtype(x) + out_depths.dtype(0.5)
    py = out_depths.dtype(y) + out_depths.dtype(0.5)
    start = tile_offsets[tile]
    end = tile_offsets[tile + 1]

    transmittance = out_depths.dtype(1.0)
    color = wp.vector(out_depths.dtype(0.0), out_depths.dtype(0.0), out_depths.dtype(0.0))
    depth = out_depths.dtype(0.0)
    last = start
    for i in range(start, end):
        g = isect_ids[i]
        sigma, dx, dy = gaussian_falloff(means2d[g], conics[g], px, py)
        if out_of_reach(sigma):
            continue
        alpha, falloff = splat_alpha(opacities[g - first_gaussian], sigma)
        if alpha == out_depths.dtype(0.0):
            continue
        next_transmittance = transmittance * (out_depths.dtype(1.0) - alpha)
        if next_transmittance <= out_depths.dtype(TRANSMITTANCE_MIN):
            break
        weight = alpha * transmittance
        color = color + weight * colors[g]
        depth = depth + weight * depths[g]
        transmittance = next_transmittance
        last = i + 1

    out_colors[pix] = color
    out_depths[pix] = depth
    out_alphas[pix] = out_depths.dtype(1.0) - transmittance
    final_transmittance[pix] = transmittance
    isect_end[pix] = last


@wp.kernel(enable_backward=False)
def rasterize_backward_kernel(
    means2d: wp.array(dtype=Any),
    conics: wp.array(dtype=Any),
    colors: wp.array(dtype=Any),
    opacities: wp.array(dtype=Any),
    depths: wp.array(dtype=Any),
    tile_offsets: wp.array(dtype=wp.int32),
    isect_ids: wp.array(dtype=wp.int32),
    num_gaussians: int,
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    first_pixel: int,
    final_transmittance: wp.array(dtype=Any),
    isect_end: wp.array(dtype=wp.int32),
    v_out_colors: wp.array(dtype=Any),
    v_out_depths: wp.array(dtype=Any),
    v_out_alphas: wp.array(dtype=Any),
    v_means2d: wp.array(dtype=Any),
    v_conics: wp.array(dtype=Any),
    v_colors: wp.array(dtype=Any),
    v_opacities: wp.array(dtype=Any),
    v_depths: wp.array(dtype=Any),
):
    cam, tile, x, y, pix = locate_pixel(first_pixel + wp.tid(), width, height, tile_size, tiles_x, tiles_y)
    if pix < 0:
        return
    first_gaussian = cam * num_gaussians
    px = v_out_depths.dtype(x) + v_out_depths.dtype(0.5)
    py = v_out_depths.dtype(y) + v_out_depths.dtype(0.5)
    start = tile_offsets[tile]

    t_final = final_transmittance[pix]
    v_color = v_out_colors[pix]
    v_depth = v_out_depths[pix]
    v_alpha_out = v_out_alphas[pix]

    transmittance = t_final
    color_behind = wp.vector(v_out_depths.dtype(0.0), v_out_depths.dtype(0.0), v_out_depths.dtype(0.0))  # sum of c_j alpha_j T_j over the Gaussians behind the current one
    depth_behind = v_out_depths.dtype(0.0)
    i = isect_end[pix]
    while i > start:
        i -= 1
        g = isect_ids[i]
        sigma, dx, dy = gaussian_falloff(means2d[g], conics[g], px, py)
        if out_of_reach(sigma):
            continue
        opacity = opacities[g - first_gaussian]
        alpha, falloff = splat_alpha(opacity, sigma)
        if alpha == v_out_depths.dtype(0.0):
            continue
        raw_alpha = opacity * falloff
        one_minus_alpha_inv = v_out_depths.dtype(1.0) / (v_out_depths.dtype(1.0) - alpha)
        transmittance = transmittance * one_minus_alpha_inv
        weight = alpha * transmittance
        c = colors[g]
        z = depths[g]
        wp.atomic_add(v_colors, g, weight * v_color)
        wp.atomic_add(v_depths, g, weight * v_depth)

        v_alpha = (
            wp.dot(c * transmittance - color_behind * one_minus_alpha_inv, v_color)
            + (z * transmittance - depth_behind * one_minus_alpha_inv) * v_depth
            + t_final * one_minus_alpha_inv * v_alpha_out
        )
        color_behind = color_behind + weight * c
        depth_behind = depth_behind + weight * z

        if raw_alpha <= v_out_depths.dtype(MAX_ALPHA):  # the 0.99 clamp has zero gradient
            wp.atomic_add(v_opacities, g - first_gaussian, falloff * v_alpha)
            v_sigma = -raw_alpha * v_alpha
            half = v_out_depths.dtype(0.5)
            wp.atomic_add(v_conics, g, wp.vector(half * dx * dx * v_sigma, dx * dy * v_sigma, half * dy * dy * v_sigma))
            # d = pixel - mean, so d(sigma)/d(mean) = -(conic d)
            wp.atomic_add(
                v_means2d,
                g,
                wp.vector(-(conics[g][0] * dx + conics[g][1] * dy) * v_sigma, -(conics[g][1] * dx + conics[g][2] * dy) * v_sigma),
            )
