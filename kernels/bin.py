"""Tile binning: which Gaussians touch which screen tiles, as (tile, depth) sort keys.

Two passes, as gsplat: count the tiles under each projected Gaussian's bounding square, then (after a prefix sum
on the host side) emit one key per (Gaussian, tile) pair. Key = tile << 32 | depth bits: the bit pattern of a
positive float32 orders like its value, so one 64-bit integer sort orders by tile, then front to back (gsplat's
trick). Camera c's tiles are numbered c * tiles_per_camera + ty * tiles_x + tx. Never differentiated.
"""

from typing import Any

import warp as wp


@wp.func
def tile_bounds(mean2d: Any, radius: int, tile_size: int, tiles_x: int, tiles_y: int):
    """Half-open tile rectangle [x0, x1) x [y0, y1) covering the square of half-width `radius` around `mean2d`."""
    r = float(radius)
    ts = float(tile_size)
    mx = float(mean2d[0])
    my = float(mean2d[1])
    x0 = wp.clamp(int(wp.floor((mx - r) / ts)), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((mx + r) / ts)) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((my - r) / ts)), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((my + r) / ts)) + 1, 0, tiles_y)
    return x0, x1, y0, y1


@wp.kernel(enable_backward=False)
def count_tiles_kernel(
    means2d: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    tile_counts: wp.array(dtype=wp.int32),
):
    gid = wp.tid()
    tile_counts[gid] = 0
    if radii[gid] <= 0:
        return
    x0, x1, y0, y1 = tile_bounds(means2d[gid], radii[gid], tile_size, tiles_x, tiles_y)
    tile_counts[gid] = (x1 - x0) * (y1 - y0)


@wp.kernel(enable_backward=False)
def emit_intersections_kernel(
    means2d: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    write_offsets: wp.array(dtype=wp.int32),
    depth_bits: wp.array(dtype=wp.int32),
    num_gaussians: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    isect_keys: wp.array(dtype=wp.int64),
    isect_ids: wp.array(dtype=wp.int32),
):
    gid = wp.tid()
    if radii[gid] <= 0:
        return
    cam = gid / num_gaussians
    x0, x1, y0, y1 = tile_bounds(means2d[gid], radii[gid], tile_size, tiles_x, tiles_y)
    depth_key = wp.int64(depth_bits[gid])
    cursor = write_offsets[gid]
    for ty in range(y0, y1):
        for tx in range(x0, x1):
            tile = cam * tiles_x * tiles_y + ty * tiles_x + tx
            isect_keys[cursor] = (wp.int64(tile) << wp.int64(32)) | depth_key
            isect_ids[cursor] = gid
            cursor += 1
