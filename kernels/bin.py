"""Tile binning: which Gaussians touch which screen tiles, each tile's list ordered front to back.

A Gaussian is listed in a tile only if its ellipse of reach -- the pixels where alpha = opacity exp(-sigma) is at
least the rasterizer's 1/255 cut-off, sigma = 1/2 d^T conic d -- meets the rectangle of the tile's pixel centres.
For each row of tiles the ellipse's x-extent within that band is found in closed form, so the test costs a few
square roots per tile row, not per tile, and drops the corners of the projection's square bounding box (about a
fifth of it for a round Gaussian, most of it for an elongated one). It is conservative (a small margin on the
threshold), so the rasterized image is the one every tile of the bounding box would give.

Two orderings, same lists:
- CUDA (gsplat): count each Gaussian's tiles, emit one key per (Gaussian, tile) after a prefix sum, key =
  tile << 32 | depth bits (the bit pattern of a positive float32 orders like its value), one 64-bit sort.
- CPU: a counting sort, linear in the number of intersections instead of a sort of them. Each camera's Gaussians
  are put front to back (one sort of the N depths); every Gaussian's tile spans, row by row, are found once, in
  parallel over ranges of Gaussians, and stored in that order. The depth order is then cut into consecutive
  chunks, one host-thread task each: a task counts its Gaussians per tile from the spans in a histogram of its
  own; the prefix sum over tiles, and within a tile over the camera's tasks in order, gives every task its own
  write cursors; then each task appends its Gaussians to their tiles. A tile's list is thus the earlier chunks'
  entries before the later ones': front to back, the same lists as one serial walk.

Camera c's tiles are numbered c * tiles_per_camera + ty * tiles_x + tx (`TileGeometry`, shared with the
rasterizer). Never differentiated.
"""

from typing import Any

import warp as wp

from warpbags.kernels.rasterize import ALPHA_THRESHOLD, TileGeometry

# Added to 2 ln(255 opacity), the reach of sigma doubled: float32 rounding in the rasterizer never meets it.
REACH_MARGIN = 2.0e-3


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


@wp.func
def reach_quadric(conic: Any, opacity: Any):
    """(a, b, c, t) with the ellipse of reach {d : a dx^2 + 2 b dx dy + c dy^2 <= t}; t < 0 if nothing reaches."""
    return (float(conic[0]), float(conic[1]), float(conic[2]),
            2.0 * wp.log(float(opacity) / ALPHA_THRESHOLD) + REACH_MARGIN)


@wp.func
def row_tile_span(mean2d: Any, a: float, b: float, c: float, t: float, ty: int, x0: int, x1: int, tile_size: int,
                  width: int, height: int):
    """Half-open tile columns [tx0, tx1) of tile row `ty`, within [x0, x1), that the ellipse of reach meets.

    The row's band is its pixel centres' y-range; the ellipse's points in the band project onto an x-interval whose
    ends are the ellipse's own x-extremes where they fall inside the band, else the band edge nearest to them (the
    boundary x(dy) is concave); the interval is then cut to the image's pixel centres, so a Gaussian that reaches a
    cut last tile only beyond the image is not listed there. A conic that is not positive definite keeps the whole
    [x0, x1).
    """
    det = a * c - b * b
    if a <= 0.0 or c <= 0.0 or det <= 0.0:
        return x0, x1
    ts = float(tile_size)
    mx = float(mean2d[0])
    my = float(mean2d[1])
    band_lo = float(ty) * ts + 0.5 - my
    band_hi = wp.min(float(ty) * ts + ts, float(height)) - 0.5 - my
    dy_reach = wp.sqrt(t * a / det)
    band_lo = wp.max(band_lo, -dy_reach)
    band_hi = wp.min(band_hi, dy_reach)
    if band_lo > band_hi:
        return x0, x0
    dx_reach = wp.sqrt(t * c / det)
    # right extreme at (dx_reach, -b dx_reach / c), left one mirrored through the centre
    dy_right = wp.clamp(-b * dx_reach / c, band_lo, band_hi)
    dy_left = wp.clamp(b * dx_reach / c, band_lo, band_hi)
    root_right = wp.sqrt(wp.max(b * b * dy_right * dy_right - a * (c * dy_right * dy_right - t), 0.0))
    root_left = wp.sqrt(wp.max(b * b * dy_left * dy_left - a * (c * dy_left * dy_left - t), 0.0))
    x_hi = wp.min(mx + (-b * dy_right + root_right) / a, float(width) - 0.5)
    x_lo = mx + (-b * dy_left - root_left) / a
    if x_lo > x_hi:
        return x0, x0
    # tile tx holds pixel centres tx * ts + 0.5 ... tx * ts + ts - 0.5
    tx0 = wp.max(int(wp.ceil((x_lo + 0.5) / ts - 1.0)), x0)
    tx1 = wp.min(int(wp.floor((x_hi - 0.5) / ts)) + 1, x1)
    return tx0, wp.max(tx1, tx0)


@wp.kernel(enable_backward=False)
def count_tiles_kernel(
    means2d: wp.array(dtype=Any),
    conics: wp.array(dtype=Any),
    opacities: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    tiles: TileGeometry,
    tile_counts: wp.array(dtype=wp.int32),
):
    gid = wp.tid()
    tile_counts[gid] = 0
    if radii[gid] <= 0:
        return
    a, b, c, t = reach_quadric(conics[gid], opacities[gid % tiles.num_gaussians])
    x0, x1, y0, y1 = tile_bounds(means2d[gid], radii[gid], tiles.tile_size, tiles.tiles_x, tiles.tiles_y)
    count = int(0)
    for ty in range(y0, y1):
        tx0, tx1 = row_tile_span(means2d[gid], a, b, c, t, ty, x0, x1, tiles.tile_size, tiles.width, tiles.height)
        count += tx1 - tx0
    tile_counts[gid] = count


@wp.kernel(enable_backward=False)
def emit_intersections_kernel(
    means2d: wp.array(dtype=Any),
    conics: wp.array(dtype=Any),
    opacities: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    write_offsets: wp.array(dtype=wp.int32),
    depth_keys: wp.array(dtype=wp.int32),
    tiles: TileGeometry,
    isect_keys: wp.array(dtype=wp.int64),
    isect_ids: wp.array(dtype=wp.int32),
):
    gid = wp.tid()
    if radii[gid] <= 0:
        return
    cam = gid / tiles.num_gaussians
    a, b, c, t = reach_quadric(conics[gid], opacities[gid % tiles.num_gaussians])
    x0, x1, y0, y1 = tile_bounds(means2d[gid], radii[gid], tiles.tile_size, tiles.tiles_x, tiles.tiles_y)
    depth_key = wp.int64(depth_keys[gid])
    cursor = write_offsets[gid]
    for ty in range(y0, y1):
        tx0, tx1 = row_tile_span(means2d[gid], a, b, c, t, ty, x0, x1, tiles.tile_size, tiles.width, tiles.height)
        for tx in range(tx0, tx1):
            tile = cam * tiles.tiles_x * tiles.tiles_y + ty * tiles.tiles_x + tx
            isect_keys[cursor] = (wp.int64(tile) << wp.int64(32)) | depth_key
            isect_ids[cursor] = gid
            cursor += 1


@wp.func
def ranked_gaussian(rank: int, depth_order: wp.array(dtype=wp.int32), tiles: TileGeometry):
    """The flat (camera, Gaussian) index of depth rank `rank` (camera-major, depth_order[c * N + k]: camera c's k-th
    Gaussian front to back)."""
    return (rank / tiles.num_gaussians) * tiles.num_gaussians + depth_order[rank]


@wp.kernel(enable_backward=False)
def tile_rows_kernel(
    means2d: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    depth_order: wp.array(dtype=wp.int32),
    tiles: TileGeometry,
    first_rows: wp.array(dtype=wp.int32),
    row_counts: wp.array(dtype=wp.int32),
):
    """Per depth rank: the first tile row of the Gaussian's bounding square and how many rows it spans (0 if
    culled)."""
    rank = wp.tid()
    gid = ranked_gaussian(rank, depth_order, tiles)
    first_rows[rank] = 0
    row_counts[rank] = 0
    if radii[gid] > 0:
        x0, x1, y0, y1 = tile_bounds(means2d[gid], radii[gid], tiles.tile_size, tiles.tiles_x, tiles.tiles_y)
        first_rows[rank] = y0
        row_counts[rank] = y1 - y0


@wp.kernel(enable_backward=False)
def tile_spans_kernel(
    means2d: wp.array(dtype=Any),
    conics: wp.array(dtype=Any),
    opacities: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    depth_order: wp.array(dtype=wp.int32),
    tiles: TileGeometry,
    row_offsets: wp.array(dtype=wp.int32),
    first_rank: int,
    spans: wp.array(dtype=wp.vec2i),
):
    """Per depth rank from `first_rank` on: the tile columns [tx0, tx1) the Gaussian's ellipse of reach meets in
    each of its rows, at spans[row_offsets[rank] + row - first row]. The ellipse work, done once and in parallel for
    the counting and filling passes, which then read the spans in order."""
    rank = first_rank + wp.tid()
    gid = ranked_gaussian(rank, depth_order, tiles)
    if radii[gid] <= 0:
        return
    a, b, c, t = reach_quadric(conics[gid], opacities[gid % tiles.num_gaussians])
    x0, x1, y0, y1 = tile_bounds(means2d[gid], radii[gid], tiles.tile_size, tiles.tiles_x, tiles.tiles_y)
    for ty in range(y0, y1):
        tx0, tx1 = row_tile_span(means2d[gid], a, b, c, t, ty, x0, x1, tiles.tile_size, tiles.width, tiles.height)
        spans[row_offsets[rank] + ty - y0] = wp.vec2i(tx0, tx1)


@wp.kernel(enable_backward=False)
def tile_histogram_kernel(
    spans: wp.array(dtype=wp.vec2i),
    row_offsets: wp.array(dtype=wp.int32),
    first_rows: wp.array(dtype=wp.int32),
    row_counts: wp.array(dtype=wp.int32),
    tiles: TileGeometry,
    chunk_starts: wp.array(dtype=wp.int32),
    chunk_stops: wp.array(dtype=wp.int32),
    first_chunk: int,
    chunk_counts: wp.array2d(dtype=wp.int32),
):
    """One thread per chunk [start, stop) of one camera's depth ranks: chunk_counts[chunk, tile] = how many of the
    chunk's Gaussians the camera's tile lists (zeroed by the caller)."""
    chunk = first_chunk + wp.tid()
    for rank in range(chunk_starts[chunk], chunk_stops[chunk]):
        for row in range(row_counts[rank]):
            span = spans[row_offsets[rank] + row]
            first_tile = (first_rows[rank] + row) * tiles.tiles_x  # among the camera's tiles
            for tx in range(span[0], span[1]):
                chunk_counts[chunk, first_tile + tx] = chunk_counts[chunk, first_tile + tx] + 1


@wp.kernel(enable_backward=False)
def fill_tiles_front_to_back_kernel(
    spans: wp.array(dtype=wp.vec2i),
    row_offsets: wp.array(dtype=wp.int32),
    first_rows: wp.array(dtype=wp.int32),
    row_counts: wp.array(dtype=wp.int32),
    depth_order: wp.array(dtype=wp.int32),
    tiles: TileGeometry,
    chunk_starts: wp.array(dtype=wp.int32),
    chunk_stops: wp.array(dtype=wp.int32),
    first_chunk: int,
    chunk_cursors: wp.array2d(dtype=wp.int32),
    isect_ids: wp.array(dtype=wp.int32),
):
    """One thread per chunk: append the chunk's Gaussians to their tiles' lists in depth order, each tile's cursor
    (`chunk_cursors[chunk, tile]`) starting where the chunk's entries of that tile go."""
    chunk = first_chunk + wp.tid()
    for rank in range(chunk_starts[chunk], chunk_stops[chunk]):
        gid = ranked_gaussian(rank, depth_order, tiles)
        for row in range(row_counts[rank]):
            span = spans[row_offsets[rank] + row]
            first_tile = (first_rows[rank] + row) * tiles.tiles_x
            for tx in range(span[0], span[1]):
                isect_ids[chunk_cursors[chunk, first_tile + tx]] = gid
                chunk_cursors[chunk, first_tile + tx] = chunk_cursors[chunk, first_tile + tx] + 1


def _declare_overloads() -> None:
    """The GPU path's kernels in both precisions, declared up front: the CPU never launches them, so without this
    a CPU machine (the CUDA code-generation test) would never build them."""
    for scalar in (wp.float32, wp.float64):
        splats = [wp.array(dtype=wp.types.vector(2, scalar)), wp.array(dtype=wp.types.vector(3, scalar)),
                  wp.array(dtype=scalar), wp.array(dtype=wp.int32)]
        wp.overload(count_tiles_kernel, [*splats, TileGeometry, wp.array(dtype=wp.int32)])
        wp.overload(emit_intersections_kernel, [*splats, wp.array(dtype=wp.int32), wp.array(dtype=wp.int32),
                                                TileGeometry, wp.array(dtype=wp.int64), wp.array(dtype=wp.int32)])


_declare_overloads()
