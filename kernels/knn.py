"""The mean distance from each point to its k nearest other points, for the floater removal (k = sqrt(N): ~316
neighbours of each of ~100k Gaussian centres).

The points are bucketed in a uniform 3-D grid by a counting sort (a count, a prefix sum, a fill: kernels/nearest.py's
fill pass). Each point then visits shells of cells around its own, outwards, keeping its k nearest so far in a
max-heap of squared distances (its own row of a scratch array), until no cell further out can hold a nearer point
than the heap's largest: a point in a cell r + 1 shells away lies at least r cell edges away. Points outside the grid
are clamped into its border cells, which keeps that bound (a clamped point is further away than its cell, never
nearer), so a few far floaters do not stretch the grid. A floater itself, outside the grid's box, would meet the
bound only when its shells had covered every cell, so it takes every point in turn instead
(warpbags.wrapper.mean_neighbour_distances gives the numbers).

Squared distances are taken in float64; the k kept are the k smallest whatever the order of the points in a cell
(on CUDA the fill's order depends on the atomics), so only the final sum's rounding depends on it.
"""

from typing import Any

import warp as wp

from warpbags.kernels.nearest import RING_SLACK, clamped_cell


@wp.struct
class PointGrid3:
    """A uniform grid of cells_x x cells_y x cells_z cubic cells of edge `cell`, lower corner at `origin`."""

    origin: wp.vec3d
    cell: wp.float64
    cells_x: int
    cells_y: int
    cells_z: int


@wp.func
def grid_cell(point: Any, grid: PointGrid3):
    """The (x, y, z) cell holding `point`, clamped into the grid."""
    return (clamped_cell(wp.float64(point[0]), grid.origin[0], grid.cell, grid.cells_x),
            clamped_cell(wp.float64(point[1]), grid.origin[1], grid.cell, grid.cells_y),
            clamped_cell(wp.float64(point[2]), grid.origin[2], grid.cell, grid.cells_z))


@wp.kernel(enable_backward=False)
def count_cells_3d_kernel(points: wp.array(dtype=Any), grid: PointGrid3, point_cells: wp.array(dtype=wp.int32),
                          cell_counts: wp.array(dtype=wp.int32)):
    """Each point's cell (x-fastest index) and the number of points per cell."""
    i = wp.tid()
    cx, cy, cz = grid_cell(points[i], grid)
    cell = (cz * grid.cells_y + cy) * grid.cells_x + cx
    point_cells[i] = cell
    wp.atomic_add(cell_counts, cell, 1)


@wp.func
def heap_push(heap: wp.array2d(dtype=wp.float64), row: int, size: int, value: wp.float64):
    """Add `value` to the max-heap heap[row, :size] (room for it is the caller's to ensure)."""
    child = size
    while child > 0:
        parent = (child - 1) / 2
        if heap[row, parent] >= value:
            break
        heap[row, child] = heap[row, parent]
        child = parent
    heap[row, child] = value


@wp.func
def heap_replace_top(heap: wp.array2d(dtype=wp.float64), row: int, size: int, value: wp.float64):
    """Replace the largest of the max-heap heap[row, :size] by the smaller `value`."""
    parent = int(0)
    while True:
        child = 2 * parent + 1
        if child >= size:
            break
        if child + 1 < size and heap[row, child + 1] > heap[row, child]:
            child = child + 1
        if heap[row, child] <= value:
            break
        heap[row, parent] = heap[row, child]
        parent = child
    heap[row, parent] = value


@wp.func
def offer(heaps: wp.array2d(dtype=wp.float64), row: int, size: int, k: int, d: wp.float64):
    """Keep squared distance `d` among the k smallest in heap row `row` of `size` entries; returns the new size."""
    if size < k:
        heap_push(heaps, row, size, d)
        return size + 1
    if d < heaps[row, 0]:
        heap_replace_top(heaps, row, size, d)
    return size


@wp.func
def squared_distance_3d(a: Any, b: Any):
    dx = wp.float64(a[0]) - wp.float64(b[0])
    dy = wp.float64(a[1]) - wp.float64(b[1])
    dz = wp.float64(a[2]) - wp.float64(b[2])
    return dx * dx + dy * dy + dz * dz


@wp.func
def inside_grid(point: Any, grid: PointGrid3):
    """Whether `point` lies in the grid's box (not clamped into it)."""
    cells = wp.vec3d(wp.float64(grid.cells_x), wp.float64(grid.cells_y), wp.float64(grid.cells_z))
    upper = grid.origin + cells * grid.cell
    return (wp.float64(point[0]) >= grid.origin[0] and wp.float64(point[0]) < upper[0]
            and wp.float64(point[1]) >= grid.origin[1] and wp.float64(point[1]) < upper[1]
            and wp.float64(point[2]) >= grid.origin[2] and wp.float64(point[2]) < upper[2])


@wp.kernel(enable_backward=False)
def mean_knn_distance_kernel(points: wp.array(dtype=Any), grid: PointGrid3, cell_offsets: wp.array(dtype=wp.int32),
                             cell_points: wp.array(dtype=wp.int32), k: int, first_point: int,
                             heaps: wp.array2d(dtype=wp.float64), mean_distances: wp.array(dtype=wp.float64)):
    """Mean distance from point first_point + tid to its k nearest other points (k < the number of points), shell
    by shell of cells; heaps[tid, :k] is the thread's scratch. A point outside the grid's box (a floater) takes
    every point in turn instead: its shells would meet the bound only after covering the whole grid, whose cells
    outnumber the points."""
    row = wp.tid()
    q = first_point + row
    query = points[q]
    size = int(0)
    if not inside_grid(query, grid):
        for j in range(points.shape[0]):
            if j != q:
                size = offer(heaps, row, size, k, squared_distance_3d(query, points[j]))
    else:
        qx, qy, qz = grid_cell(query, grid)
        last_shell = wp.max(wp.max(grid.cells_x, grid.cells_y), grid.cells_z)
        for shell in range(last_shell + 1):
            for cz in range(wp.max(qz - shell, 0), wp.min(qz + shell, grid.cells_z - 1) + 1):
                for cy in range(wp.max(qy - shell, 0), wp.min(qy + shell, grid.cells_y - 1) + 1):
                    # on the shell's two z faces and two y faces every cell of the row, between them only its ends
                    step = 1
                    if shell > 0 and wp.abs(cz - qz) != shell and wp.abs(cy - qy) != shell:
                        step = 2 * shell
                    for cx in range(qx - shell, qx + shell + 1, step):
                        if cx >= 0 and cx < grid.cells_x:
                            cell = (cz * grid.cells_y + cy) * grid.cells_x + cx
                            for slot in range(cell_offsets[cell], cell_offsets[cell + 1]):
                                j = cell_points[slot]
                                if j != q:
                                    size = offer(heaps, row, size, k, squared_distance_3d(query, points[j]))
            reach = (wp.float64(shell) - wp.float64(RING_SLACK)) * grid.cell  # the least distance to the next shell
            if size == k and reach > wp.float64(0.0) and heaps[row, 0] <= reach * reach:
                break
    total = wp.float64(0.0)
    for i in range(size):
        total += wp.sqrt(heaps[row, i])
    mean_distances[q] = total / wp.float64(wp.max(size, 1))
