"""Thin torch wrappers around the Warp kernels, one per stage (gsplat's layout).

Projection, spherical harmonics and the pose transform have no dynamic loops, so their gradients come from Warp's
Tape. The rasterizer has a hand-written backward kernel (see kernels/rasterize.py). Binning is not differentiable.

Tensors stay where they are: CPU tensors run on Warp's "cpu" device, CUDA tensors on the matching CUDA device and
the current torch stream, without host copies. float32 and float64 are both supported (float64 for gradchecks).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, nullcontext
from typing import NamedTuple, Sequence

import torch
import warp as wp

from warpbags.kernels.bin import (
    count_tiles_kernel,
    emit_intersections_kernel,
    fill_tiles_front_to_back_kernel,
    tile_histogram_kernel,
)
from warpbags.kernels.pose import apply_object_deltas_kernel, apply_pose_deltas_kernel
from warpbags.kernels.project import project_gaussians_kernel
from warpbags.kernels.rasterize import BACKWARD_KERNELS, FORWARD_KERNELS
from warpbags.kernels.sh import sh_to_colors_kernel

_WP_SCALARS = {torch.float32: wp.float32, torch.float64: wp.float64}

# Warp value type of each tensor "kind": the trailing tensor dimensions it consumes.
_KIND_SHAPES = {"scalar": (), "vec2": (2,), "vec3": (3,), "vec4": (4,), "mat33": (3, 3), "mat44": (4, 4)}


def _warp_dtype(kind: str, scalar: torch.dtype):
    if kind == "int32":
        return wp.int32
    if kind == "int64":
        return wp.int64
    base = _WP_SCALARS[scalar]
    shape = _KIND_SHAPES[kind]
    if len(shape) == 0:
        return base
    if len(shape) == 1:
        return wp.types.vector(shape[0], base)
    return wp.types.matrix(shape, base)


def _to_warp(tensor: torch.Tensor, kind: str, grad: torch.Tensor | None = None) -> wp.array:
    """Zero-copy Warp view of a contiguous tensor; `grad`, if given, becomes the array's adjoint buffer."""
    wp.init()  # idempotent; deferred to first use so importing warpbags has no side effects
    dtype = _warp_dtype(kind, tensor.dtype)
    if grad is None:
        return wp.from_torch(tensor, dtype=dtype, requires_grad=False)
    return wp.from_torch(tensor, dtype=dtype, requires_grad=True, grad=grad)


class _Launcher(NamedTuple):
    """Where a stage's kernels run: the Warp device of its tensors and, on CUDA, torch's current stream there.

    Every launch names both, so host worker threads never rely on Warp's process-wide default device (which
    `wp.ScopedDevice` would set for every thread at once), and CUDA work stays ordered with torch's.
    """

    device: object  # warp Device
    stream: object  # wp.Stream on CUDA, None on the CPU

    def launch(self, kernel, dim, inputs: Sequence = (), outputs: Sequence = ()) -> None:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device, stream=self.stream)


def _launcher(device: torch.device) -> _Launcher:
    """The launcher for tensors on `device`."""
    wp.init()
    stream = wp.stream_from_torch(device) if device.type == "cuda" else None
    return _Launcher(wp.device_from_torch(device), stream)


def _launch_scope(device: torch.device) -> ExitStack:
    """Make `device` Warp's default device (and torch's current stream its stream) for the block.

    Only for callers whose launches do not name their device (warpbags/losses.py); the stages here use
    `_Launcher`. The scope is process-wide, not per thread.
    """
    scope = ExitStack()
    scope.enter_context(wp.ScopedDevice(wp.device_from_torch(device)))
    if device.type == "cuda":
        scope.enter_context(wp.ScopedStream(wp.stream_from_torch(device)))
    return scope


class _TapedKernel(torch.autograd.Function):
    """Launch one Warp kernel under a Tape; backward replays the tape with the incoming cotangents.

    `input_kinds[i]` is the Warp kind of argument i: "vec3", "mat44", ... for tensors, "float" for a Python number
    passed in the tensors' precision, None for any other plain argument.
    `output_specs` are (kind, shape) of the kernel's outputs, allocated here as zeros; integer outputs are marked
    non-differentiable. When no input tensor requires a gradient (rendering for evaluation), the kernel runs
    without a Tape and no adjoint buffers are allocated.
    """

    @staticmethod
    def forward(ctx, kernel, dim, input_kinds, output_specs, *args):
        tensors = [a for a in args if isinstance(a, torch.Tensor)]
        needs_grad = any(t.requires_grad for t in tensors)
        device = tensors[0].device
        scalar = next(t.dtype for t in tensors if t.is_floating_point())
        wp_inputs, input_grads = [], []
        for arg, kind in zip(args, input_kinds):
            if kind is None or kind == "float":
                wp_inputs.append(arg if kind is None else _WP_SCALARS[scalar](arg))
                input_grads.append(None)
                continue
            value = arg.detach().contiguous()
            grad = torch.zeros_like(value) if value.is_floating_point() and arg.requires_grad else None
            wp_inputs.append(_to_warp(value, kind, grad))
            input_grads.append(grad)

        outputs, wp_outputs = [], []
        for kind, shape in output_specs:
            is_float = kind not in ("int32", "int64")
            dtype = scalar if is_float else getattr(torch, kind)
            value = torch.zeros((*shape, *_KIND_SHAPES.get(kind, ())), dtype=dtype, device=device)
            grad = torch.zeros_like(value) if is_float and needs_grad else None
            outputs.append(value)
            wp_outputs.append(_to_warp(value, kind, grad))

        tape = wp.Tape() if needs_grad else None
        with tape or nullcontext():
            _launcher(device).launch(kernel, dim, wp_inputs, wp_outputs)
        ctx.tape, ctx.device = tape, device
        ctx.wp_outputs, ctx.input_grads = wp_outputs, input_grads
        ctx.mark_non_differentiable(*[o for o in outputs if not o.is_floating_point()])
        return tuple(outputs)

    @staticmethod
    def backward(ctx, *v_outputs):
        # The adjoint kernel accumulates into the input gradient buffers: clear them so a second backward through
        # the same graph (retain_graph, gradcheck) starts from zero, and hand torch copies it may keep.
        for grad in ctx.input_grads:
            if grad is not None:
                grad.zero_()
        with _launch_scope(ctx.device):  # the Tape replays its launches on the default device's stream
            cotangents = {}
            for wp_out, v_out in zip(ctx.wp_outputs, v_outputs):
                if wp_out.requires_grad and v_out is not None:
                    wp.copy(wp_out.grad, wp.from_torch(v_out.contiguous(), dtype=wp_out.dtype))
                    cotangents[wp_out] = wp_out.grad
            if cotangents:
                ctx.tape.backward(grads=cotangents)
        input_grads = [None if grad is None else grad.clone() for grad in ctx.input_grads]
        return (None, None, None, None, *input_grads)


def apply_pose_deltas(viewmats: torch.Tensor, pose_deltas: torch.Tensor) -> torch.Tensor:
    """`exp(pose_deltas) @ viewmats`.

    Args:
        viewmats: [C, 4, 4] world-to-camera matrices.
        pose_deltas: [C, 6] se(3) corrections ordered [wx, wy, wz, vx, vy, vz] (axis-angle rotation, then the
            translation part of the twist), applied on the left (in the camera frame).

    Returns:
        [C, 4, 4] corrected world-to-camera matrices; differentiable in both inputs.
    """
    cams = viewmats.shape[0]
    (out,) = _TapedKernel.apply(
        apply_pose_deltas_kernel, cams, ("mat44", "scalar"), [("mat44", (cams,))], viewmats, pose_deltas
    )
    return out



def apply_object_deltas(viewmats: torch.Tensor, params: torch.Tensor, object_centers: torch.Tensor) -> torch.Tensor:
    """Object-centric corrections (CamP's; see kernels/pose.py).

    Args:
        viewmats: [C, 4, 4] world-to-camera matrices.
        params: [C, 6] [wx, wy, wz, ux, uy, s]: rotation about the object centre, image shift (focal lengths), log
            depth.
        object_centers: [C, 3] the object centre (world) each camera turns about.

    Returns:
        [C, 4, 4] corrected world-to-camera matrices; differentiable in every input.
    """
    cams = viewmats.shape[0]
    (out,) = _TapedKernel.apply(
        apply_object_deltas_kernel, cams, ("mat44", "scalar", "vec3"), [("mat44", (cams,))],
        viewmats, params, object_centers,
    )
    return out


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection of N Gaussians into C cameras.

    Args:
        means: [N, 3] centres. quats: [N, 4] (w, x, y, z), any norm. scales: [N, 3] linear.
        opacities: [N] in [0, 1] (only for the opacity-aware radius). viewmats: [C, 4, 4] world-to-camera.
        Ks: [C, 3, 3] pinhole intrinsics. near_plane, far_plane: depth culling. eps2d: low-pass added to the 2D
        covariance, in pixels^2.

    Returns:
        means2d [C, N, 2] pixels, conics [C, N, 3] (upper triangle of the inverse 2D covariance), depths [C, N]
        camera z, radii [C, N] int32 (0 = culled). Culled entries of the float outputs are zero.
    """
    cams, n = viewmats.shape[0], means.shape[0]
    return _TapedKernel.apply(
        project_gaussians_kernel,
        (cams, n),
        ("vec3", "vec4", "vec3", "scalar", "mat44", "mat33", None, None, "float", "float", "float"),
        [("vec2", (cams, n)), ("vec3", (cams, n)), ("scalar", (cams, n)), ("int32", (cams, n))],
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
    )


def spherical_harmonics(means: torch.Tensor, coeffs: torch.Tensor, viewmats: torch.Tensor, degree: int) -> torch.Tensor:
    """View-dependent colour max(SH(dir) + 0.5, 0) with dir from each camera centre to each Gaussian.

    Args:
        means: [N, 3]. coeffs: [N, K, 3] with K >= (degree + 1)^2. viewmats: [C, 4, 4] world-to-camera.
        degree: active SH degree, 0-3.

    Returns:
        [C, N, 3] colours; differentiable in means, coeffs and viewmats.
    """
    cams, n = viewmats.shape[0], means.shape[0]
    (colors,) = _TapedKernel.apply(
        sh_to_colors_kernel, (cams, n), ("vec3", "vec3", "mat44", None), [("vec3", (cams, n))], means, coeffs, viewmats, degree
    )
    return colors


class TileBins(NamedTuple):
    """Gaussian/tile intersections sorted by tile, then depth.

    tile_offsets: [C * tiles_y * tiles_x + 1] int32, the intersections of tile t are isect_ids[offsets[t]:offsets[t+1]].
    isect_ids: [M] int32 flat index cam * N + gaussian.
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    tile_offsets: torch.Tensor
    isect_ids: torch.Tensor


@torch.no_grad()
def bin_gaussians(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, radii: torch.Tensor,
                  depths: torch.Tensor, width: int, height: int, tile_size: int,
                  cpu_threads: int | None = None) -> TileBins:
    """List every tile's Gaussians front to back: those whose ellipse of reach meets the tile (kernels/bin.py).

    Args:
        means2d: [C, N, 2]. conics: [C, N, 3]. opacities: [N]. radii: [C, N] int32 (0 = culled). depths: [C, N].
        width, height: image size in pixels. tile_size: tile edge in pixels.
        cpu_threads: host threads for CPU tensors (cameras are binned in parallel); ignored on CUDA.
    """
    cams, n = radii.shape
    device = radii.device
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    num_tiles = cams * tiles_x * tiles_y
    splats = [_to_warp(means2d.detach().reshape(-1, 2).contiguous(), "vec2"),
              _to_warp(conics.detach().reshape(-1, 3).contiguous(), "vec3"),
              _to_warp(opacities.detach().contiguous(), "scalar"), _to_warp(radii.reshape(-1).contiguous(), "int32")]
    geometry = [n, tile_size, tiles_x, tiles_y, height]
    if device.type == "cuda":
        tile_offsets, isect_ids = _bin_by_sort(splats, geometry, depths, num_tiles)
    else:
        tile_offsets, isect_ids = _bin_by_counting(splats, geometry, radii, depths, num_tiles,
                                                   cpu_threads or _default_cpu_threads())
    return TileBins(tile_size, tiles_x, tiles_y, tile_offsets, isect_ids)


def _bin_by_sort(splats: list, geometry: list, depths: torch.Tensor, num_tiles: int):
    """gsplat's binning: one (tile, depth) key per intersection, sorted (the GPU path)."""
    device = depths.device
    launcher = _launcher(device)
    counts = torch.empty(depths.numel(), dtype=torch.int32, device=device)
    launcher.launch(count_tiles_kernel, depths.numel(), [*splats, *geometry], [_to_warp(counts, "int32")])
    ends = torch.cumsum(counts, 0, dtype=torch.int64)
    num_isects = int(ends[-1]) if ends.numel() else 0
    write_offsets = (ends - counts).to(torch.int32)
    # Culled Gaussians emit nothing, so every depth used here is > near_plane > 0.
    depth_bits = depths.detach().reshape(-1).to(torch.float32).contiguous().view(torch.int32)
    keys = torch.empty(num_isects, dtype=torch.int64, device=device)
    ids = torch.empty(num_isects, dtype=torch.int32, device=device)
    if num_isects:
        launcher.launch(
            emit_intersections_kernel, depths.numel(),
            [*splats, _to_warp(write_offsets, "int32"), _to_warp(depth_bits, "int32"), *geometry],
            [_to_warp(keys, "int64"), _to_warp(ids, "int32")],
        )
    keys, order = torch.sort(keys)
    tile_offsets = torch.searchsorted(keys >> 32, torch.arange(num_tiles + 1, device=device)).to(torch.int32)
    return tile_offsets, ids[order].contiguous()


def _bin_by_counting(splats: list, geometry: list, radii: torch.Tensor, depths: torch.Tensor, num_tiles: int,
                     threads: int):
    """Counting sort by tile of the depth-ordered Gaussians (the CPU path): one serial pass per camera to count,
    one to fill; cameras run in parallel host threads (Warp launches release the GIL)."""
    cams = radii.shape[0]
    launcher = _launcher(radii.device)
    tile_counts = torch.zeros(num_tiles, dtype=torch.int32)
    cameras = [(cam, cam + 1) for cam in range(cams)]
    counts_wp = _to_warp(tile_counts, "int32")

    def count(worker, first, stop):
        launcher.launch(tile_histogram_kernel, stop - first, [*splats, *geometry, first], [counts_wp])

    _for_each_worker(count, cameras, min(threads, cams))
    tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.int32)
    torch.cumsum(tile_counts, 0, dtype=torch.int32, out=tile_offsets[1:])
    isect_ids = torch.empty(int(tile_offsets[-1]), dtype=torch.int32)
    # Culled Gaussians last; a stable sort keeps equal depths in index order (deterministic lists).
    depth_keys = torch.where(radii > 0, depths.detach(), torch.full_like(depths, math.inf))
    depth_order = torch.argsort(depth_keys, dim=1, stable=True).to(torch.int32)
    tile_cursors = tile_offsets[:-1].clone()
    order_wp, cursors_wp, ids_wp = _to_warp(depth_order, "int32"), _to_warp(tile_cursors, "int32"), _to_warp(isect_ids, "int32")

    def fill(worker, first, stop):
        launcher.launch(fill_tiles_front_to_back_kernel, stop - first, [*splats, order_wp, *geometry, first],
                        [cursors_wp, ids_wp])

    if len(isect_ids):
        _for_each_worker(fill, cameras, min(threads, cams))
    return tile_offsets, isect_ids


def _default_cpu_threads() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def _pixel_ranges(num_tiles: int, items_per_tile: int, num_chunks: int) -> list[tuple[int, int]]:
    """Split the tile-major index space (pixels or pixel blocks, `items_per_tile` per tile) into tile-aligned
    [start, stop) ranges: the first tile alone (it runs before the threads start, see `_for_each_worker`), then
    `num_chunks` ranges over the rest."""
    if num_tiles == 0:
        return []
    bounds = torch.linspace(1, num_tiles, num_chunks + 1).round().long().tolist()
    tiles = [(0, 1)] + [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    return [(a * items_per_tile, b * items_per_tile) for a, b in tiles]


def _for_each_worker(work, ranges: list[tuple[int, int]], workers: int) -> None:
    """Run work(worker, start, stop) over the ranges, each worker in its own thread on every workers-th range.

    Warp CPU launches release the GIL, so host threads over disjoint tiles run in parallel. The first range runs
    alone so that a kernel's first-use compilation happens once, not in every thread at the same time.
    """
    if not ranges:
        return
    work(0, *ranges[0])
    rest = ranges[1:]

    def run(worker: int) -> None:
        for start, stop in rest[worker::workers]:
            work(worker, start, stop)

    if workers == 1:
        run(0)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(run, range(workers)))


# Pixels one rasterizer thread composites, (width, height) within a tile. On CUDA one pixel per thread (gsplat's
# layout: threads are cheap, registers are not). On the CPU a thread walks its tile's list once for a block of
# pixels, so each Gaussian's loads (and the gradient adds of the backward) serve every pixel of the block.
# Measured on 2 cores loaded by other work (wall ms of the rasterizer stage, forward + backward, min of 6, blocks
# in turn in one process), bench/rasterize.py's 128^2 / 10k / 4-camera scene and maryrose 432^2 after 50 steps
# from the random init (127 Gaussians per pixel, 95% contributing): 4-pixel tiles, blocks 1x1 / 2x2 / 4x1:
# 162 / 141 / 126 and 1843 / 1548 / 1499; 8-pixel tiles, 2x2 / 4x2 / 2x4: 152 / 131 / 148 and 1539 / 1370 / 1402.
# Compare with bench/rasterize.py --blocks and bench/train_step.py --pixel-blocks.
# None: 4x1 for tiles of 4 pixels or less, 4x2 for larger ones.
DEFAULT_PIXEL_BLOCK: dict[str, tuple[int, int] | None] = {"cuda": (1, 1), "cpu": None}


def _pixel_block(device: torch.device, tile_size: int, block: tuple[int, int] | None) -> tuple[int, int]:
    """The block for this device and tile: each side the largest divisor of the tile size not above the asked one
    (a block never spans two tiles), and a pixel count the kernels are built for."""
    block = block or DEFAULT_PIXEL_BLOCK["cuda" if device.type == "cuda" else "cpu"]
    block_w, block_h = block or ((4, 1) if tile_size <= 4 else (4, 2))
    block_w = max(d for d in range(1, min(block_w, tile_size) + 1) if tile_size % d == 0)
    block_h = max(d for d in range(1, min(block_h, tile_size) + 1) if tile_size % d == 0)
    if block_w * block_h not in FORWARD_KERNELS:
        raise ValueError(f"pixel block {block_w}x{block_h}: the rasterizer is built for {sorted(FORWARD_KERNELS)} pixels per thread")
    return block_w, block_h


# Per-Gaussian rasterizer inputs in kernel argument order (means2d, conics, colors, opacities, depths), flattened
# over cameras; the backward kernel's gradient outputs come in the same order.
_SPLAT_KINDS = ("vec2", "vec3", "vec3", "scalar", "scalar")


def _splat_arguments(splats: Sequence[torch.Tensor], bins: TileBins, geometry: tuple) -> list:
    """The arguments both rasterizer kernels start with: the splats, the tile bins and the image geometry."""
    return [*(_to_warp(t, kind) for t, kind in zip(splats, _SPLAT_KINDS)), _to_warp(bins.tile_offsets, "int32"),
            _to_warp(bins.isect_ids, "int32"), *geometry]


class _RasterizeToPixels(torch.autograd.Function):
    """Forward and hand-written backward rasterization kernels; see kernels/rasterize.py."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, bins: TileBins, width, height, cpu_threads,
                pixel_block):
        cams, n = depths.shape
        device, scalar = means2d.device, means2d.dtype
        splats = (
            means2d.detach().reshape(-1, 2).contiguous(),
            conics.detach().reshape(-1, 3).contiguous(),
            colors.detach().reshape(-1, 3).contiguous(),
            opacities.detach().contiguous(),
            depths.detach().reshape(-1).contiguous(),
        )
        pixels = cams * height * width
        out_colors = torch.zeros(cams, height, width, 3, dtype=scalar, device=device)
        out_depths = torch.zeros(cams, height, width, dtype=scalar, device=device)
        out_alphas = torch.zeros(cams, height, width, dtype=scalar, device=device)
        final_transmittance = torch.ones(cams, height, width, dtype=scalar, device=device)
        isect_end = torch.zeros(cams, height, width, dtype=torch.int32, device=device)

        outputs = [
            _to_warp(out_colors.view(pixels, 3), "vec3"), _to_warp(out_depths.view(pixels), "scalar"),
            _to_warp(out_alphas.view(pixels), "scalar"), _to_warp(final_transmittance.view(pixels), "scalar"),
            _to_warp(isect_end.view(pixels), "int32"),
        ]
        workers = 1 if device.type == "cuda" else (cpu_threads or _default_cpu_threads())
        block_w, block_h = _pixel_block(device, bins.tile_size, pixel_block)
        ctx.lanes = block_w * block_h
        ctx.geometry = (n, width, height, bins.tile_size, bins.tiles_x, bins.tiles_y, block_w, block_h)
        common = _splat_arguments(splats, bins, ctx.geometry)
        blocks_per_tile = bins.tile_size**2 // ctx.lanes
        ranges = _pixel_ranges(cams * bins.tiles_x * bins.tiles_y, blocks_per_tile, 1 if workers == 1 else 8 * workers)
        kernel = FORWARD_KERNELS[ctx.lanes]
        launcher = _launcher(device)

        def work(worker, start, stop):
            launcher.launch(kernel, stop - start, [*common, start], outputs)

        _for_each_worker(work, ranges, workers)

        ctx.bins, ctx.workers, ctx.ranges = bins, workers, ranges
        ctx.save_for_backward(*splats, final_transmittance, isect_end)
        ctx.mark_non_differentiable(final_transmittance, isect_end)
        return out_colors, out_depths, out_alphas, final_transmittance, isect_end

    @staticmethod
    def backward(ctx, v_out_colors, v_out_depths, v_out_alphas, _v_transmittance, _v_isect_end):
        *splats, final_transmittance, isect_end = ctx.saved_tensors
        bins, workers = ctx.bins, ctx.workers
        pixels = final_transmittance.numel()
        device, scalar = final_transmittance.device, final_transmittance.dtype

        def cotangent(v, *shape):
            if v is None:
                return torch.zeros(*shape, dtype=scalar, device=device)
            return v.contiguous().view(*shape)

        common = _splat_arguments(splats, bins, ctx.geometry)
        saved = [
            _to_warp(final_transmittance.view(pixels), "scalar"), _to_warp(isect_end.view(pixels), "int32"),
            _to_warp(cotangent(v_out_colors, pixels, 3), "vec3"), _to_warp(cotangent(v_out_depths, pixels), "scalar"),
            _to_warp(cotangent(v_out_alphas, pixels), "scalar"),
        ]
        # One private set of gradient buffers per worker: CPU atomics are plain adds.
        buffers = [[torch.zeros_like(t) for t in splats] for _ in range(workers)]
        wp_buffers = [[_to_warp(t, kind) for t, kind in zip(b, _SPLAT_KINDS)] for b in buffers]

        kernel = BACKWARD_KERNELS[ctx.lanes]
        launcher = _launcher(device)

        def work(worker, start, stop):
            launcher.launch(kernel, stop - start, [*common, start, *saved], wp_buffers[worker])

        _for_each_worker(work, ctx.ranges, workers)

        v_means2d, v_conics, v_colors, v_opacities, v_depths = (sum(parts[1:], parts[0]) for parts in zip(*buffers))
        cams, n = final_transmittance.shape[0], ctx.geometry[0]
        return (
            v_means2d.view(cams, n, 2), v_conics.view(cams, n, 3), v_colors.view(cams, n, 3), v_opacities,
            v_depths.view(cams, n), None, None, None, None, None,
        )


def rasterize_to_pixels(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    cpu_threads: int | None = None,
    pixel_block: tuple[int, int] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Alpha-composite the binned Gaussians of every camera.

    Args:
        means2d: [C, N, 2]. conics: [C, N, 3]. colors: [C, N, 3]. opacities: [N]. depths: [C, N].
        bins: from `bin_gaussians`. width, height: image size. cpu_threads: host threads for CPU tensors
            (default: the cores this process may use); ignored on CUDA.
        pixel_block: (width, height) of the pixels one thread composites (default `DEFAULT_PIXEL_BLOCK` of the
            device); each side is reduced to a divisor of the tile size. Results are the same for every block up to
            float rounding of the gradient sums.

    Returns:
        colors [C, H, W, 3] (no background), depths [C, H, W] (alpha-weighted camera z), alphas [C, H, W];
        all differentiable.
    """
    out_colors, out_depths, out_alphas, _, _ = _RasterizeToPixels.apply(
        means2d, conics, colors, opacities, depths, bins, width, height, cpu_threads, pixel_block
    )
    return out_colors, out_depths, out_alphas
