"""Rasterization: front-to-back alpha compositing per pixel over its tile's depth-sorted Gaussians.

Forward, per pixel:  alpha_i = min(0.99, opacity_i * exp(-sigma_i)),  sigma_i = 1/2 d^T conic_i d,
    C = sum_i c_i alpha_i T_i,  D = sum_i z_i alpha_i T_i,  T_i = prod_{j<i} (1 - alpha_j),  A = 1 - T_final.
Contributions with alpha < 1/255 are skipped, and compositing stops before a Gaussian that would bring the
transmittance to 1e-4 or below (gsplat's rule). The forward saves T_final and the end of the contributing range.

The backward is written by hand and walks the same list back to front, recovering T_i = T_{i+1} / (1 - alpha_i):
Warp's automatic adjoint of this dynamic loop is silently wrong (dynamic loops are not replayed), so neither
kernel is differentiated by Warp.

One thread composites a block of block_w x block_h pixels of one tile (`lanes` = block_w * block_h, a kernel built
per lane count): it reads each Gaussian of the tile's list once for all its pixels, and the backward sums the
block's gradients of a Gaussian before adding them to the buffers once. Each pixel keeps its own transmittance,
colour, end of range and termination, with the same arithmetic as one pixel per thread, so the image is the same
bit for bit and the gradients differ only by float rounding of the per-block sums. CUDA runs one pixel per thread
(lanes = 1, gsplat's layout); the CPU a block of 16 (see warpbags/wrapper.py).

The lanes do not branch: a pixel that a Gaussian does not reach, that has terminated or that is past its range gets
alpha = 0 (`splat_alpha`) and adds exact zeros, so the result is that of skipping it, and the compiler turns the
lanes into vector instructions. For the same reason float32 takes exp(-sigma) from an inline polynomial
(`gaussian_weight`, within 2.1e-6 relative) instead of a library call; float64 keeps the library exponential.

Blocks are visited tile-major (all blocks of a tile, then the next tile) so a launch over a range of tiles touches
one Gaussian list at a time; `first_block` offsets the launch so host threads can take disjoint tile ranges. The
image and its tiles come in one `TileGeometry` (shared with kernels/bin.py).
Gradient buffers are written with atomic adds: on CUDA one buffer, on CPU one private buffer per range of tiles
(CPU atomics are plain adds; see warpbags/wrapper.py).

It stays one module because the forward and backward kernels are one stage: the backward replays the forward's
block layout, termination rule and `@wp.func` helpers exactly, and splitting them would separate what must agree.
"""

from typing import Any

import warp as wp

ALPHA_THRESHOLD = 1.0 / 255.0
SIGMA_CUTOFF = 5.545177444479562  # ln(255)
MAX_ALPHA = 0.99
TRANSMITTANCE_MIN = 1.0e-4

# CPU build: LLVM's default SLP vectorizer depth. Warp's default CPU flags add -slp-recursion-max-depth=4 (and higher
# inlining thresholds), which leaves most of the lanes' arithmetic scalar. Kernels alone, 128^2 / 4 cameras / 10k
# Gaussians, one thread: forward 15.5-19 -> 8.6-9.3 ms, backward 30-36 -> 26-28 ms. The CUDA build ignores it.
wp.set_module_options({"cpu_compiler_flags": "-march=native"})


@wp.struct
class TileGeometry:
    """The image and its tiles, as binning (kernels/bin.py) and rasterization see them. Camera c's tile (tx, ty) is
    number c * tiles_x * tiles_y + ty * tiles_x + tx and holds the pixels from (tx, ty) * tile_size on."""

    num_gaussians: int  # N per camera: the flat index of Gaussian g in camera c is c * N + g
    width: int
    height: int
    tile_size: int  # tile edge in pixels
    tiles_x: int  # ceil(width / tile_size)
    tiles_y: int  # ceil(height / tile_size)


@wp.func
def gaussian_falloff(mean2d: Any, conic: Any, px: Any, py: Any):
    """sigma = 1/2 d^T conic d with d = pixel centre - mean; also returns d."""
    dx = px - mean2d[0]
    dy = py - mean2d[1]
    half = type(dx)(0.5)
    sigma = half * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
    return sigma, dx, dy


@wp.func
def gaussian_weight(sigma: wp.float32):
    """exp(-sigma) for 0 <= sigma <= ln(255) in float32, as (Taylor polynomial of degree 7 of exp(-sigma/16))^16:
    within 2.1e-6 relative (the library's expf: 1.9e-7). Inline arithmetic instead of a library call, so that the
    branch-free lanes of a pixel block compile to vector code (a call per lane kept them scalar)."""
    x = sigma * wp.float32(0.0625)
    p = wp.float32(1.0 / 720.0) - x * wp.float32(1.0 / 5040.0)
    p = wp.float32(1.0 / 120.0) - x * p
    p = wp.float32(1.0 / 24.0) - x * p
    p = wp.float32(1.0 / 6.0) - x * p
    p = wp.float32(0.5) - x * p
    p = wp.float32(1.0) - x * p
    p = wp.float32(1.0) - x * p
    p = p * p
    p = p * p
    p = p * p
    return p * p


@wp.func
def gaussian_weight(sigma: wp.float64):
    """exp(-sigma) in float64: the library exponential, at the precision the reference and gradient tests check."""
    return wp.exp(-sigma)


@wp.func
def splat_alpha(opacity: Any, sigma: Any, active: Any):
    """(alpha, opacity exp(-sigma), exp(-sigma)) of one pixel, branch-free.

    alpha = min(0.99, opacity exp(-sigma)), or 0 where `active` is 0 (the pixel is outside the image, terminated or
    past its contributing range), where no opacity can make the Gaussian count (sigma < 0, a numerically indefinite
    conic, or sigma > ln(255), where even opacity 1 gives alpha < 1/255) or below the 1/255 cut-off. A pixel with
    alpha 0 then adds exact zeros, so the result is that of skipping it.
    """
    zero = type(sigma)(0.0)
    cutoff = type(sigma)(SIGMA_CUTOFF)
    in_reach = wp.where(sigma < zero, zero, wp.where(sigma > cutoff, zero, active))
    falloff = gaussian_weight(wp.clamp(sigma, zero, cutoff))
    raw_alpha = opacity * falloff
    alpha = wp.min(type(sigma)(MAX_ALPHA), raw_alpha)
    alpha = wp.where(alpha < type(sigma)(ALPHA_THRESHOLD), zero, alpha) * in_reach
    return alpha, raw_alpha, falloff


@wp.func
def locate_block(index: int, tiles: TileGeometry, block_w: int, block_h: int):
    """Tile-major block index -> (camera, global tile, x, y of the block's top-left pixel). A tile's blocks of
    block_w x block_h pixels (both dividing tile_size) are numbered row-major within it."""
    blocks_x = tiles.tile_size / block_w
    blocks_per_tile = blocks_x * (tiles.tile_size / block_h)
    tiles_per_cam = tiles.tiles_x * tiles.tiles_y
    tile = index / blocks_per_tile
    local = index - tile * blocks_per_tile
    cam = tile / tiles_per_cam
    tile_in_cam = tile - cam * tiles_per_cam
    ty = tile_in_cam / tiles.tiles_x
    tx = tile_in_cam - ty * tiles.tiles_x
    by = local / blocks_x
    x = tx * tiles.tile_size + (local - by * blocks_x) * block_w
    y = ty * tiles.tile_size + by * block_h
    return cam, tile, x, y


@wp.func
def lane_pixel(x0: int, y0: int, lane: int, block_w: int, cam: int, width: int, height: int):
    """Pixel (x, y) of lane `lane` of the block whose top-left pixel is (x0, y0), and its flat output index
    (camera-major, row-major), -1 outside the image."""
    x = x0 + lane % block_w
    y = y0 + lane / block_w
    pix = int(-1)
    if x < width and y < height:
        pix = (cam * height + y) * width + x
    return x, y, pix


def _lane_sum(lanes: int):
    """Sum of a vector of `lanes` (a power of two up to 16) values as a tree of halves, which the compiler turns into
    a few vector additions (a running sum, lane after lane, fixes the order of the float additions and stays scalar)."""
    assert lanes in (1, 2, 4, 8, 16), lanes

    @wp.func
    def lane_sum(v: Any):
        s = v
        for k in range(wp.static(lanes // 2)):
            s[k] = s[k] + s[k + wp.static(lanes // 2)]
        for k in range(wp.static(lanes // 4)):
            s[k] = s[k] + s[k + wp.static(lanes // 4)]
        for k in range(wp.static(lanes // 8)):
            s[k] = s[k] + s[k + wp.static(lanes // 8)]
        for k in range(wp.static(lanes // 16)):
            s[k] = s[k] + s[k + wp.static(lanes // 16)]
        return s[0]

    return lane_sum


def _forward_kernel(lanes: int):
    """The forward kernel for blocks of `lanes` pixels per thread (block_w * block_h == lanes)."""

    lane_sum = _lane_sum(lanes)

    @wp.kernel(enable_backward=False)
    def rasterize_forward_kernel(
        means2d: wp.array(dtype=Any),
        conics: wp.array(dtype=Any),
        colors: wp.array(dtype=Any),
        opacities: wp.array(dtype=Any),
        depths: wp.array(dtype=Any),
        tile_offsets: wp.array(dtype=wp.int32),
        isect_ids: wp.array(dtype=wp.int32),
        tiles: TileGeometry,
        block_w: int,
        block_h: int,
        first_block: int,
        out_colors: wp.array(dtype=Any),
        out_depths: wp.array(dtype=Any),
        out_alphas: wp.array(dtype=Any),
        final_transmittance: wp.array(dtype=Any),
        isect_end: wp.array(dtype=wp.int32),
    ):
        cam, tile, x0, y0 = locate_block(first_block + wp.tid(), tiles, block_w, block_h)
        zero = out_depths.dtype(0.0)
        one = out_depths.dtype(1.0)
        # per-lane state: pixel centre, output index, whether the lane still composites (1: inside the image and not
        # terminated), transmittance, colour, depth and the end of the contributing range
        px = wp.vector(zero, length=wp.static(lanes))
        py = wp.vector(zero, length=wp.static(lanes))
        pix = wp.vector(wp.int32(-1), length=wp.static(lanes))
        live = wp.vector(zero, length=wp.static(lanes))
        transmittance = wp.vector(one, length=wp.static(lanes))
        red = wp.vector(zero, length=wp.static(lanes))
        green = wp.vector(zero, length=wp.static(lanes))
        blue = wp.vector(zero, length=wp.static(lanes))
        depth = wp.vector(zero, length=wp.static(lanes))
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1]
        # The end of each lane's contributing range, counted from `start`, in floats, and the early exit from a sum
        # of the live lanes: the lanes' update then compiles to vector blends, where an int32 per lane (and a count
        # of the live lanes) stayed scalar code. Exact in float32 below 2^24 entries in a tile's list, which the
        # wrapper ensures (no more than 2^24 Gaussians per camera).
        last = wp.vector(zero, length=wp.static(lanes))
        for k in range(wp.static(lanes)):
            x, y, lane_pix = lane_pixel(x0, y0, k, block_w, cam, tiles.width, tiles.height)
            px[k] = out_depths.dtype(x) + out_depths.dtype(0.5)
            py[k] = out_depths.dtype(y) + out_depths.dtype(0.5)
            if lane_pix >= 0:
                pix[k] = lane_pix
                live[k] = one
        if lane_sum(live) == zero:
            return
        # isect ids are flat (camera, Gaussian) indices and opacities per Gaussian: one subtraction per visit
        first_gaussian = cam * tiles.num_gaussians
        t_min = out_depths.dtype(TRANSMITTANCE_MIN)

        for i in range(start, end):
            g = isect_ids[i]
            past_i = out_depths.dtype(i + 1 - start)
            mean = means2d[g]
            conic = conics[g]
            opacity = opacities[g - first_gaussian]
            c = colors[g]
            z = depths[g]
            # every lane does the same arithmetic (no branches, so the lanes vectorize); a lane the Gaussian does
            # not reach has alpha 0 and adds exact zeros
            for k in range(wp.static(lanes)):
                sigma, dx, dy = gaussian_falloff(mean, conic, px[k], py[k])
                alpha, raw_alpha, falloff = splat_alpha(opacity, sigma, live[k])
                next_transmittance = transmittance[k] * (one - alpha)
                # the pixel stops before a Gaussian that would bring its transmittance to 1e-4 or below
                stops = wp.where(next_transmittance <= t_min, wp.where(alpha > zero, one, zero), zero)
                weight = alpha * transmittance[k] * (one - stops)
                red[k] = red[k] + weight * c[0]
                green[k] = green[k] + weight * c[1]
                blue[k] = blue[k] + weight * c[2]
                depth[k] = depth[k] + weight * z
                transmittance[k] = wp.where(stops > zero, transmittance[k], next_transmittance)
                last[k] = wp.where(stops > zero, last[k], wp.where(alpha > zero, past_i, last[k]))
                live[k] = live[k] * (one - stops)
            if lane_sum(live) == zero:
                break

        for k in range(wp.static(lanes)):
            if pix[k] >= 0:
                out_colors[pix[k]] = wp.vector(red[k], green[k], blue[k])
                out_depths[pix[k]] = depth[k]
                out_alphas[pix[k]] = one - transmittance[k]
                final_transmittance[pix[k]] = transmittance[k]
                isect_end[pix[k]] = start + int(last[k])

    return rasterize_forward_kernel


def _backward_kernel(lanes: int, with_depth: bool):
    """The backward kernel for blocks of `lanes` pixels per thread: the lanes' gradients of one Gaussian are
    summed (`_lane_sum`) and added to the buffers once. Without `with_depth` the depth map's cotangent is taken as
    zero: its terms are left out and v_depths is not written.

    Per pixel (lane), with v the pixel's colour cotangent (and depth cotangent), walking back to front:
        T_i = T_{i+1} / (1 - alpha_i),  dL/dc_i = alpha_i T_i v,
        dL/dalpha_i = T_i (c_i . v) - (sum_{j>i} alpha_j T_j (c_j . v) - T_final v_A) / (1 - alpha_i),
    so a lane carries one running sum `behind` (started at -T_final v_A) instead of one per channel. The shape's
    gradient is summed as the moments sum(dx v_sigma), sum(dy v_sigma), sum(dx dx v_sigma), sum(dx dy v_sigma),
    sum(dy dy v_sigma) over the lanes, and turned into the conic's and the mean's gradients once per Gaussian."""

    lane_sum = _lane_sum(lanes)

    @wp.kernel(enable_backward=False)
    def rasterize_backward_kernel(
        means2d: wp.array(dtype=Any),
        conics: wp.array(dtype=Any),
        colors: wp.array(dtype=Any),
        opacities: wp.array(dtype=Any),
        depths: wp.array(dtype=Any),
        tile_offsets: wp.array(dtype=wp.int32),
        isect_ids: wp.array(dtype=wp.int32),
        tiles: TileGeometry,
        block_w: int,
        block_h: int,
        first_block: int,
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
        cam, tile, x0, y0 = locate_block(first_block + wp.tid(), tiles, block_w, block_h)
        zero = v_out_depths.dtype(0.0)
        one = v_out_depths.dtype(1.0)
        half = v_out_depths.dtype(0.5)
        px = wp.vector(zero, length=wp.static(lanes))
        py = wp.vector(zero, length=wp.static(lanes))
        v_red = wp.vector(zero, length=wp.static(lanes))
        v_green = wp.vector(zero, length=wp.static(lanes))
        v_blue = wp.vector(zero, length=wp.static(lanes))
        v_depth = wp.vector(zero, length=wp.static(lanes))
        # lane k composited list entries [start, start + last[k]) (floats, as in the forward: with an int32 per lane
        # the lanes' arithmetic vectorized 4 lanes at a time instead of 16)
        last = wp.vector(zero, length=wp.static(lanes))
        transmittance = wp.vector(one, length=wp.static(lanes))
        # sum of alpha_j T_j (c_j . v) (+ z_j v_depth) over the Gaussians behind the current one, minus T_final v_A
        behind = wp.vector(zero, length=wp.static(lanes))
        start = tile_offsets[tile]
        i = int(0)
        for k in range(wp.static(lanes)):
            x, y, pix = lane_pixel(x0, y0, k, block_w, cam, tiles.width, tiles.height)
            px[k] = v_out_depths.dtype(x) + v_out_depths.dtype(0.5)
            py[k] = v_out_depths.dtype(y) + v_out_depths.dtype(0.5)
            if pix >= 0:
                transmittance[k] = final_transmittance[pix]
                v_color = v_out_colors[pix]
                v_red[k] = v_color[0]
                v_green[k] = v_color[1]
                v_blue[k] = v_color[2]
                if wp.static(with_depth):
                    v_depth[k] = v_out_depths[pix]
                behind[k] = -transmittance[k] * v_out_alphas[pix]
                last[k] = v_out_depths.dtype(isect_end[pix] - start)
                i = wp.max(i, isect_end[pix])
        first_gaussian = cam * tiles.num_gaussians
        # each lane's share of the current Gaussian's gradients, summed over the lanes after the lanes loop
        lane_red = wp.vector(zero, length=wp.static(lanes))
        lane_green = wp.vector(zero, length=wp.static(lanes))
        lane_blue = wp.vector(zero, length=wp.static(lanes))
        lane_depth = wp.vector(zero, length=wp.static(lanes))
        lane_opacity = wp.vector(zero, length=wp.static(lanes))
        lane_x = wp.vector(zero, length=wp.static(lanes))  # dx v_sigma
        lane_y = wp.vector(zero, length=wp.static(lanes))  # dy v_sigma
        lane_xx = wp.vector(zero, length=wp.static(lanes))  # dx dx v_sigma
        lane_xy = wp.vector(zero, length=wp.static(lanes))  # dx dy v_sigma
        lane_yy = wp.vector(zero, length=wp.static(lanes))  # dy dy v_sigma
        lane_colored = wp.vector(zero, length=wp.static(lanes))  # 1 where the lane composited the Gaussian
        lane_shaped = wp.vector(zero, length=wp.static(lanes))  # 1 where, besides, alpha is below the 0.99 clamp

        while i > start:
            i -= 1
            g = isect_ids[i]
            mean = means2d[g]
            conic = conics[g]
            opacity = opacities[g - first_gaussian]
            c = colors[g]
            z = depths[g]
            rank = v_out_depths.dtype(i - start)
            for k in range(wp.static(lanes)):
                sigma, dx, dy = gaussian_falloff(mean, conic, px[k], py[k])
                alpha, raw_alpha, falloff = splat_alpha(opacity, sigma, wp.where(rank < last[k], one, zero))
                one_minus_alpha_inv = one / (one - alpha)
                transmittance[k] = transmittance[k] * one_minus_alpha_inv
                weight = alpha * transmittance[k]
                lane_red[k] = weight * v_red[k]
                lane_green[k] = weight * v_green[k]
                lane_blue[k] = weight * v_blue[k]
                color_dot = c[0] * v_red[k] + c[1] * v_green[k] + c[2] * v_blue[k]
                if wp.static(with_depth):
                    lane_depth[k] = weight * v_depth[k]
                    color_dot = color_dot + z * v_depth[k]
                v_alpha = transmittance[k] * color_dot - behind[k] * one_minus_alpha_inv
                behind[k] = behind[k] + weight * color_dot
                composited = wp.where(alpha > zero, one, zero)
                lane_colored[k] = composited
                shape = wp.where(raw_alpha <= v_out_depths.dtype(MAX_ALPHA), composited, zero)  # the clamp's gradient is 0
                lane_shaped[k] = shape
                v_alpha = v_alpha * shape
                lane_opacity[k] = falloff * v_alpha
                v_sigma = -raw_alpha * v_alpha
                lane_x[k] = dx * v_sigma
                lane_y[k] = dy * v_sigma
                lane_xx[k] = dx * lane_x[k]
                lane_xy[k] = dx * lane_y[k]
                lane_yy[k] = dy * lane_y[k]
            # On the CPU (lanes > 1) the sums are added unconditionally, exact zeros where no lane contributed: a
            # branch on them splits the lanes' arithmetic into blocks the compiler vectorizes 4 lanes at a time.
            # One pixel per thread (CUDA) adds only what a composited pixel gives, as gsplat does.
            colored = wp.static(lanes > 1) or lane_colored[0] != zero
            shaped = wp.static(lanes > 1) or lane_shaped[0] != zero
            if colored:
                wp.atomic_add(v_colors, g, wp.vector(lane_sum(lane_red), lane_sum(lane_green), lane_sum(lane_blue)))
                if wp.static(with_depth):
                    wp.atomic_add(v_depths, g, lane_sum(lane_depth))
            if shaped:
                wp.atomic_add(v_opacities, g - first_gaussian, lane_sum(lane_opacity))
                sum_x = lane_sum(lane_x)
                sum_y = lane_sum(lane_y)
                wp.atomic_add(v_conics, g, wp.vector(half * lane_sum(lane_xx), lane_sum(lane_xy), half * lane_sum(lane_yy)))
                # d = pixel - mean, so d(sigma)/d(mean) = -(conic d)
                wp.atomic_add(v_means2d, g, wp.vector(-(conic[0] * sum_x + conic[1] * sum_y),
                                                      -(conic[1] * sum_x + conic[2] * sum_y)))

    return rasterize_backward_kernel


# Pixels per thread the kernels are built for. One pixel per thread is the CUDA layout (gsplat's); on the CPU a
# thread composites a block of a tile so that each Gaussian read serves several pixels (warpbags/wrapper.py picks).
LANES = (1, 2, 4, 8, 16)
FORWARD_KERNELS = {lanes: _forward_kernel(lanes) for lanes in LANES}
# keyed (lanes, with_depth): training without a depth loss takes the kernel without the depth terms
BACKWARD_KERNELS = {(lanes, with_depth): _backward_kernel(lanes, with_depth) for lanes in LANES
                    for with_depth in (True, False)}


def _declare_overloads() -> None:
    """Every (lanes, precision) variant, declared up front: the module builds once with all of them (instead of
    once more at each variant's first launch), and the CUDA variants are in it whatever ran first."""
    for scalar in (wp.float32, wp.float64):
        vec2, vec3 = wp.types.vector(2, scalar), wp.types.vector(3, scalar)
        splats = [wp.array(dtype=vec2), wp.array(dtype=vec3), wp.array(dtype=vec3), wp.array(dtype=scalar),
                  wp.array(dtype=scalar), wp.array(dtype=wp.int32), wp.array(dtype=wp.int32), TileGeometry, int, int,
                  int]
        for lanes in LANES:
            wp.overload(FORWARD_KERNELS[lanes], [
                *splats, wp.array(dtype=vec3), wp.array(dtype=scalar), wp.array(dtype=scalar), wp.array(dtype=scalar),
                wp.array(dtype=wp.int32)])
            for with_depth in (True, False):
                wp.overload(BACKWARD_KERNELS[lanes, with_depth], [
                    *splats, wp.array(dtype=scalar), wp.array(dtype=wp.int32), wp.array(dtype=vec3),
                    wp.array(dtype=scalar), wp.array(dtype=scalar), wp.array(dtype=vec2), wp.array(dtype=vec3),
                    wp.array(dtype=vec3), wp.array(dtype=scalar), wp.array(dtype=scalar)])


_declare_overloads()
