"""Thin torch wrappers around the Warp kernels, one per stage (gsplat's layout).

The pose transforms' gradients come from Warp's Tape: a stage that torch differentiates records its launch on a
Tape of its own (explicitly, never as the current Tape, so other threads' launches cannot land on it), and torch's
backward runs that Tape's backward, the adjoint kernel Warp generates. Nothing is recorded when torch records no
gradients. The projection (kernels/project.py: Warp's adjoint took three times the forward), spherical harmonics
(kernels/sh.py: Warp's adjoint 1.7 times the hand-written one) and the rasterizer (kernels/rasterize.py) have
hand-written backward kernels, as has the photometric loss (kernels/loss.py: L1 and SSIM fused in row and column
passes). Binning is not differentiable. Every backward here gives first derivatives only: its gradients are
Warp kernels' results, constants to torch, so under `create_graph` it refuses (`_first_derivatives_only`).

Tensors stay where they are: CPU tensors run on Warp's "cpu" device, CUDA tensors on the matching CUDA device and
the current torch stream, without host copies (binning reads back one number, the intersection count that
sizes its buffers, as gsplat does); every launch names its device and stream. Kernel arguments are
passed by parameter name. float32 and float64 are both supported (float64 for gradchecks).

It stays one module, as gsplat's `_wrapper.py` does, because it is one thing, the torch-Warp bridge: one
autograd stage per kernel, the launch plumbing they share, and the CPU host-thread rasterizer that splits one
launch over disjoint tile ranges; a stage read apart from its launcher or its thread split would not read whole.
"""

from __future__ import annotations

import contextlib
import functools
import math
from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F
import warp as wp

from warpbags.blur import gaussian_taps
from warpbags.kernels.bin import (
    count_tiles_kernel,
    emit_intersections_kernel,
    fill_tiles_front_to_back_kernel,
    tile_histogram_kernel,
    tile_rows_kernel,
    tile_spans_kernel,
)
from warpbags.kernels.coherence import least_outside_sample_kernel
from warpbags.kernels.knn import PointGrid3, count_cells_3d_kernel, mean_knn_distance_kernel
from warpbags.kernels.loss import (
    RUN,
    SSIM_SIGMA,
    WINDOW_RADIUS,
    photometric_grad_kernel,
    ssim_column_pass_kernel,
    ssim_grad_row_pass_kernel,
    ssim_row_pass_kernel,
)
from warpbags.kernels.nearest import PointGrid, count_cells_kernel, fill_cells_kernel, nearest_in_grid_kernel
from warpbags.kernels.pose import apply_object_deltas_kernel, apply_pose_deltas_kernel
from warpbags.kernels.project import project_gaussians_backward_kernel, project_gaussians_kernel
from warpbags.kernels.rasterize import BACKWARD_KERNELS, FORWARD_KERNELS, TileGeometry
from warpbags.kernels.sh import sh_to_colors_backward_kernel, sh_to_colors_kernel
from warpbags.threads import host_threads, thread_pool

_WP_SCALARS = {torch.float32: wp.float32, torch.float64: wp.float64}

# Warp value type of each tensor "kind": the trailing tensor dimensions it consumes.
_KIND_SHAPES = {"scalar": (), "vec2": (2,), "vec3": (3,), "vec4": (4,), "vec8": (8,), "mat33": (3, 3), "mat44": (4, 4)}


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


def _parameter_names(kernel) -> tuple[str, ...]:
    return tuple(arg.label for arg in kernel.adj.args)


class _Launcher(NamedTuple):
    """Where a stage's kernels run: the Warp device of its tensors and, on CUDA, torch's current stream there.

    Every launch names both, so host worker threads never rely on Warp's process-wide default device (which
    `wp.ScopedDevice` would set for every thread at once), and CUDA work stays ordered with torch's. No launch is
    recorded on a current Tape: a differentiable stage records its own launch on its own Tape.
    """

    device: object  # warp Device
    stream: object  # wp.Stream on CUDA, None on the CPU

    def launch(self, kernel, dim, /, **arguments) -> None:
        """Launch `kernel` with every argument given by its parameter name (a missing or unknown name raises)."""
        values = _ordered_arguments(kernel, arguments)
        wp.launch(_overload(kernel, values), dim=dim, inputs=values, device=self.device, stream=self.stream,
                  record_tape=False)


def _ordered_arguments(kernel, arguments: dict) -> list:
    """`arguments` (parameter name -> value) in the order of `kernel`'s parameters.

    Raises:
        TypeError: a parameter without a value, or a value for no parameter.
    """
    names = _parameter_names(kernel)
    if arguments.keys() != set(names):
        raise TypeError(f"kernel {kernel.key}: missing arguments {[n for n in names if n not in arguments]}, "
                        f"unknown {[n for n in arguments if n not in names]}")
    return [arguments[name] for name in names]


_OVERLOADS: dict[tuple, object] = {}


def _overload(kernel, values: list):
    """The concrete overload of a generic kernel (`Any`-typed parameters) for these arguments, resolved once per
    kernel and argument types: Warp infers it from the arguments at every launch, ~0.2 ms for the projection
    kernels' 20 parameters, six launches per rendering pass."""
    if not kernel.is_generic:
        return kernel
    key = (kernel, *((type(v), getattr(v, "dtype", None), getattr(v, "ndim", None)) for v in values))
    if key not in _OVERLOADS:
        _OVERLOADS[key] = kernel.add_overload(kernel.infer_argument_types(values))
    return _OVERLOADS[key]


def _launcher(device: torch.device) -> _Launcher:
    """The launcher for tensors on `device`."""
    wp.init()
    stream = wp.stream_from_torch(device) if device.type == "cuda" else None
    return _Launcher(wp.device_from_torch(device), stream)


class _Stage(NamedTuple):
    """A kernel without dynamic loops and the kind of each of its parameters: how `_stage_forward` launches it, and
    for the pose transforms how `_DifferentiableStage` records it on a Tape.

    `inputs` maps the kernel's input parameters, by name and in order, to their kinds: "vec3", "mat44", ... for
    tensors, "float" for a Python number passed in the tensors' precision, None for any other plain value.
    `outputs` maps its output parameters to their kinds; they are allocated as zeros, all with one array shape.
    `gaussian_inputs`: for a kernel launched over (cameras, Gaussians) whose outputs are [C, N, ...], the inputs
    indexed by the Gaussian alone. Such a stage runs on the CPU in ranges of Gaussians on the host threads (a CPU
    launch is one serial loop), those inputs and the outputs sliced to the range; so does its hand-written backward
    kernel (`_backward_over_ranges`).
    """

    kernel: object
    inputs: dict[str, str | None]
    outputs: dict[str, str]
    gaussian_inputs: frozenset[str] = frozenset()


def _stage(kernel, outputs: dict[str, str], gaussian_inputs: tuple[str, ...] = (), **inputs: str | None) -> _Stage:
    if (*inputs, *outputs) != _parameter_names(kernel):
        raise TypeError(f"kernel {kernel.key} takes {_parameter_names(kernel)}, declared {(*inputs, *outputs)}")
    return _Stage(kernel, inputs, outputs, frozenset(gaussian_inputs))


_POSE_DELTAS = _stage(apply_pose_deltas_kernel, {"out_viewmats": "mat44"}, viewmats="mat44", pose_deltas="scalar")
_OBJECT_DELTAS = _stage(apply_object_deltas_kernel, {"out_viewmats": "mat44"}, viewmats="mat44",
                        object_params="scalar", object_centers="vec3")
# The projection's forward launch; its gradient comes from its hand-written backward kernel (`_ProjectGaussians`).
_PROJECTION = _stage(
    project_gaussians_kernel, {"means2d": "vec2", "conics": "vec3", "depths": "scalar", "radii": "int32"},
    gaussian_inputs=("means", "quats", "scales", "opacities"),
    means="vec3", quats="vec4", scales="vec3", opacities="scalar", viewmats="mat44", Ks="mat33", width=None,
    height=None, near_plane="float", far_plane="float", eps2d="float",
)
_SH_COLORS = _stage(sh_to_colors_kernel, {"colors": "vec3"}, gaussian_inputs=("means", "coeffs"), means="vec3",
                    coeffs="vec3", viewmats="mat44", degree=None)


def _output_tensor(kind: str, shape: tuple, scalar: torch.dtype, device: torch.device) -> torch.Tensor:
    dtype = scalar if kind in _KIND_SHAPES else getattr(torch, kind)
    return torch.zeros((*shape, *_KIND_SHAPES.get(kind, ())), dtype=dtype, device=device)


def _warp_inputs(stage: _Stage, args: Sequence, scalar: torch.dtype, grads: Sequence | None = None) -> dict:
    """The stage's inputs as Warp arguments, by parameter name: tensors as zero-copy views, with `grads[i]` (where
    given and not None) as input i's adjoint buffer."""
    arguments = {}
    for i, ((name, kind), arg) in enumerate(zip(stage.inputs.items(), args)):
        if kind is None:
            arguments[name] = arg
        elif kind == "float":
            arguments[name] = _WP_SCALARS[scalar](arg)
        else:
            arguments[name] = _to_warp(arg.detach().contiguous(), kind, None if grads is None else grads[i])
    return arguments


def _floating_dtype(args: Sequence) -> torch.dtype:
    return next(a.dtype for a in args if isinstance(a, torch.Tensor) and a.is_floating_point())


def _tensor_device(args: Sequence) -> torch.device:
    return next(a.device for a in args if isinstance(a, torch.Tensor))


# Fewest (camera, Gaussian) pairs per host thread for a stage to be cut into Gaussian ranges: every range costs its
# Warp views, a pool hand-over and, in the backward, a private buffer of per-camera gradients. Measured
# (bench/train_step.py, bench/rasterize.py) with the projection's Tape adjoint, before its hand-written backward, and
# not re-measured since: at 1 x 10k pairs 9-11 ms wall cut in two against 6-7 in one launch; at 4 x 10k, 8 ms
# against 16.
MIN_PAIRS_PER_THREAD = 16384


def _first_alone_then_equal(count: int, parts: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of range(count): the first item alone (`_run_ranges` runs the first range alone, so a
    kernel's first-use compilation happens once), then `parts` about equal ranges of the rest; empty ones left out."""
    bounds = [min(1, count) + round(i * max(count - 1, 0) / parts) for i in range(parts + 1)]
    return [(a, b) for a, b in zip([0, *bounds], bounds) if b > a]


def _first_alone_then_chunks(count: int, chunk: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of range(count) (count >= 1): the first item alone (as `_first_alone_then_equal`), then
    ranges of `chunk` items, the last one shorter."""
    return [(0, 1)] + [(a, min(a + chunk, count)) for a in range(1, count, chunk)]


class _GaussianRanges(NamedTuple):
    """How a stage's launch is cut: `ranges` of the Gaussian index (None: one launch over the whole `dim`)."""

    dim: object
    ranges: list[tuple[int, int]] | None

    @staticmethod
    def of(stage: _Stage, dim, device: torch.device, cpu_threads: int | None = None) -> _GaussianRanges:
        """A single Gaussian first (it runs alone: first-use compilation happens once), then one range per host
        thread (`cpu_threads`, default `_default_cpu_threads`); one launch on CUDA, on one core, for stages that
        are not over Gaussians and below `MIN_PAIRS_PER_THREAD` pairs per thread."""
        workers = (cpu_threads or _default_cpu_threads()) if device.type == "cpu" else 1
        if not stage.gaussian_inputs or workers == 1 or dim[0] * dim[1] < MIN_PAIRS_PER_THREAD * workers:
            return _GaussianRanges(dim, None)
        return _GaussianRanges(dim, _first_alone_then_equal(dim[1], workers))

    def launch_dim(self, cut: tuple[int, int] | None):
        return self.dim if cut is None else (self.dim[0], cut[1] - cut[0])

    def run(self, work) -> None:
        """work(i, cut) for every launch i, cut = (start, stop) of the Gaussians or None for all."""
        if self.ranges is None:
            work(0, None)
        else:
            _run_ranges(lambda i, start, stop: work(i, (start, stop)), self.ranges, len(self.ranges) - 1)


def _cut(tensor, cut: tuple[int, int] | None, axis: int):
    """The tensor's slice `cut` along `axis` (a view), or the tensor itself for no cut or a non-tensor."""
    if cut is None or not isinstance(tensor, torch.Tensor):
        return tensor
    return tensor.narrow(axis, cut[0], cut[1] - cut[0])


def _stage_arguments(stage: _Stage, args: Sequence, outputs: Sequence, cut, scalar: torch.dtype,
                     grads: Sequence | None = None) -> dict:
    """Warp arguments of one launch over the Gaussians `cut`: per-Gaussian inputs and the outputs sliced; `grads`
    (already cut), where given, the inputs' adjoint buffers."""
    arguments = _warp_inputs(stage, [_cut(a, cut, 0) if name in stage.gaussian_inputs else a
                                     for name, a in zip(stage.inputs, args)], scalar, grads)
    arguments.update((name, _to_warp(_cut(out, cut, 1), kind)) for (name, kind), out in zip(stage.outputs.items(),
                                                                                          outputs))
    return arguments


def _stage_forward(stage: _Stage, dim, shape: tuple, args: Sequence,
                   cpu_threads: int | None = None) -> tuple[torch.Tensor, ...]:
    """Run the stage on `args` (its inputs in order), on `cpu_threads` host threads for CPU tensors (default
    `_default_cpu_threads`); returns its output tensors."""
    device = _tensor_device(args)
    scalar = _floating_dtype(args)
    outputs = [_output_tensor(kind, shape, scalar, device) for kind in stage.outputs.values()]
    launcher = _launcher(device)
    cuts = _GaussianRanges.of(stage, dim, device, cpu_threads)

    def work(_, cut):
        launcher.launch(stage.kernel, cuts.launch_dim(cut), **_stage_arguments(stage, args, outputs, cut, scalar))

    cuts.run(work)
    return tuple(outputs)


def _run_stage(stage: _Stage, dim, shape: tuple, **inputs) -> tuple[torch.Tensor, ...]:
    """Launch `stage` over `dim` threads with its inputs by parameter name; outputs are arrays of `shape`.

    Differentiable when torch records gradients and an input tensor requires one: the backward then records the
    launch on a Warp Tape and runs the Tape's backward. Otherwise (torch.no_grad(), inference_mode(), or nothing to
    differentiate) the kernel just runs: no autograd node, no adjoint buffers.
    """
    if inputs.keys() != stage.inputs.keys():
        raise TypeError(f"kernel {stage.kernel.key} takes inputs {list(stage.inputs)}, got {list(inputs)}")
    args = [inputs[name] for name in stage.inputs]
    if torch.is_grad_enabled() and any(isinstance(a, torch.Tensor) and a.requires_grad for a in args):
        return _DifferentiableStage.apply(stage, dim, shape, *args)
    return _stage_forward(stage, dim, shape, args)


_SAVED = object()  # stands for a tensor argument kept with save_for_backward


def _first_derivatives_only(function: str) -> None:
    """Called first in every backward here. The gradients come out of Warp kernels into fresh buffers, outside
    torch's graph: under `create_graph` (grad mode on in the backward) they would be constants, and a second
    derivative (a Hessian-vector product) would silently lack every term through `function`. The same rule as
    `threads._JoinedTerm`."""
    if torch.is_grad_enabled():
        raise RuntimeError(f"{function}: first derivatives only (the backward is a Warp kernel, outside torch's graph; "
                           "create_graph / double backward is not supported)")


class _DifferentiableStage(torch.autograd.Function):
    """A `_Stage` under autograd, for the pose transforms (per camera, float outputs, one launch): backward records
    the stage's launch on a Warp Tape and runs the Tape's backward (the kernel's Warp-generated adjoint) with torch's
    cotangents.

    Inputs and outputs are kept only with `save_for_backward`: Warp views of the outputs held on `ctx` would keep
    the outputs alive, and through their autograd node the whole graph, in a cycle Python's collector cannot see
    (it leaked every step's stage buffers). The recorded launch replays the forward exactly: the inputs pass
    autograd's version check when read back, so an in-place change between forward and backward fails instead of
    silently giving the gradient at the changed values.
    """

    @staticmethod
    def forward(ctx, stage, dim, shape, *args):
        outputs = _stage_forward(stage, dim, shape, args)
        ctx.stage, ctx.dim = stage, dim
        ctx.plain_args = [_SAVED if isinstance(a, torch.Tensor) else a for a in args]
        ctx.save_for_backward(*[a for a in args if isinstance(a, torch.Tensor)], *outputs)
        return outputs

    @staticmethod
    def backward(ctx, *v_outputs):
        _first_derivatives_only(f"kernel {ctx.stage.kernel.key}")
        stage = ctx.stage
        saved = ctx.saved_tensors  # reading them runs autograd's version check
        tensor_count = len(saved) - len(stage.outputs)
        inputs, outputs = iter(saved[:tensor_count]), saved[tensor_count:]
        args = [next(inputs) if a is _SAVED else a for a in ctx.plain_args]
        # Fresh buffers every backward: torch may keep a returned gradient as a parameter's .grad.
        input_grads = [torch.zeros_like(a, memory_format=torch.contiguous_format)
                       if needs and isinstance(a, torch.Tensor) and a.is_floating_point() else None
                       for a, needs in zip(args, ctx.needs_input_grad[3:])]
        launcher = _launcher(_tensor_device(args))
        arguments = _stage_arguments(stage, args, outputs, None, _floating_dtype(args), input_grads)
        tape = wp.Tape()
        tape.record_launch(stage.kernel, ctx.dim, 0, [arguments[name] for name in _parameter_names(stage.kernel)], [],
                           launcher.device)
        # The Tape launches on its recorded device, on that device's current stream: torch's, on CUDA. The adjoint of
        # a store consumes and clears its output's adjoint, so the Tape gets copies of torch's cotangents.
        with wp.ScopedStream(launcher.stream) if launcher.stream is not None else contextlib.nullcontext():
            tape.backward(grads={arguments[name]: _to_warp(v.contiguous().clone(), kind)
                                 for (name, kind), v in zip(stage.outputs.items(), v_outputs)})
        return (None, None, None, *input_grads)


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
    (out,) = _run_stage(_POSE_DELTAS, cams, (cams,), viewmats=viewmats, pose_deltas=pose_deltas)
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
    (out,) = _run_stage(_OBJECT_DELTAS, cams, (cams,), viewmats=viewmats, object_params=params,
                        object_centers=object_centers)
    return out


def _backward_over_ranges(stage: _Stage, kernel, *, gaussians: dict, cameras: dict, pairs: dict, cotangents: dict,
                          cpu_threads: int | None, **plain) -> dict[str, torch.Tensor]:
    """Launch `kernel`, the hand-written backward of `stage` (a kernel over (cameras, Gaussians)), over the Gaussian
    ranges its forward ran in (`_GaussianRanges`), and return the gradients of `gaussians` and `cameras` by name.

    Arguments by the backward kernel's parameter names: `gaussians` the stage's per-Gaussian inputs [N, ...] (cut
    with the range), `cameras` its per-camera inputs (whole), `pairs` saved outputs [C, N, ...] (cut along the
    Gaussians' axis 1), `cotangents` torch's gradients of outputs (passed as v_<output>, cut as `pairs`), `plain`
    the other arguments. The kernel accumulates the gradient of each of `gaussians` and `cameras` into v_<name>.
    `cpu_threads`: the host threads the forward was given (None: `_default_cpu_threads`).

    A range's per-Gaussian gradients are slices of one buffer (the ranges are disjoint); its per-camera gradients
    go to a private buffer (CPU atomics are plain adds, so two host threads must not share one), summed in range
    order: the gradients do not depend on which thread ran which range. Fresh buffers every backward: torch may
    keep a returned gradient as a parameter's .grad.
    """
    kinds = {**stage.inputs, **stage.outputs}

    def views(tensors: dict, cut, axis: int, prefix: str = "") -> dict:
        return {prefix + name: _to_warp(_cut(t, cut, axis), kinds[name]) for name, t in tensors.items()}

    gaussians = {name: t.detach().contiguous() for name, t in gaussians.items()}
    cameras = {name: t.detach().contiguous() for name, t in cameras.items()}
    pairs = {**{name: t.detach().contiguous() for name, t in pairs.items()},
             **{"v_" + name: t.contiguous() for name, t in cotangents.items()}}
    kinds.update(("v_" + name, kinds[name]) for name in cotangents)
    v_gaussians = {name: torch.empty_like(t) for name, t in gaussians.items()}  # each range zeroes its own slice
    some = next(iter(pairs.values()))
    cuts = _GaussianRanges.of(stage, tuple(some.shape[:2]), some.device, cpu_threads)
    # The first range, which runs alone before the others start, shares the second one's camera gradients.
    v_cameras = [{name: torch.zeros_like(t) for name, t in cameras.items()}
                 for _ in range(1 if cuts.ranges is None else max(len(cuts.ranges) - 1, 1))]
    wp_cameras = [views(buffers, None, 0, "v_") for buffers in v_cameras]
    common = {**views(cameras, None, 0), **plain}
    launcher = _launcher(some.device)

    def work(i, cut):
        for buffer in v_gaussians.values():
            _cut(buffer, cut, 0).zero_()
        launcher.launch(kernel, cuts.launch_dim(cut), **common, **views(gaussians, cut, 0), **views(pairs, cut, 1),
                        **views(v_gaussians, cut, 0, "v_"), **wp_cameras[max(i - 1, 0)])

    cuts.run(work)
    return {**v_gaussians, **{name: sum(parts[1:], parts[0])
                              for name, parts in zip(cameras, zip(*(b.values() for b in v_cameras)))}}


class _ProjectGaussians(torch.autograd.Function):
    """`project_gaussians` under autograd: the forward kernel as `_stage_forward` runs it, and the hand-written
    backward kernel (kernels/project.py) over the same Gaussian ranges (`_backward_over_ranges`).

    The inputs and the radii (which tell the culled pairs) are kept with `save_for_backward`, so an in-place change
    to an input between forward and backward fails autograd's version check. The opacity only culls: it gets no
    gradient.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
                cpu_threads):
        cams, n = viewmats.shape[0], means.shape[0]
        outputs = _stage_forward(_PROJECTION, (cams, n), (cams, n), (means, quats, scales, opacities, viewmats, Ks,
                                                                       width, height, near_plane, far_plane, eps2d),
                                 cpu_threads)
        radii = outputs[3]
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, radii)
        ctx.width, ctx.height, ctx.eps2d, ctx.cpu_threads = width, height, eps2d, cpu_threads
        ctx.mark_non_differentiable(radii)
        return outputs

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        _first_derivatives_only("project_gaussians")
        means, quats, scales, viewmats, Ks, radii = ctx.saved_tensors
        grads = _backward_over_ranges(
            _PROJECTION, project_gaussians_backward_kernel, gaussians=dict(means=means, quats=quats, scales=scales),
            cameras=dict(viewmats=viewmats, Ks=Ks), pairs=dict(radii=radii),
            cotangents=dict(means2d=v_means2d, conics=v_conics, depths=v_depths), cpu_threads=ctx.cpu_threads,
            width=ctx.width, height=ctx.height, eps2d=_WP_SCALARS[means.dtype](ctx.eps2d))
        grads = (grads["means"], grads["quats"], grads["scales"], None, grads["viewmats"], grads["Ks"])
        return (*(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad)), *[None] * 6)


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
    cpu_threads: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection of N Gaussians into C cameras.

    Args:
        means: [N, 3] centres. quats: [N, 4] (w, x, y, z), any norm. scales: [N, 3] linear.
        opacities: [N] in [0, 1] (only for the opacity-aware radius). viewmats: [C, 4, 4] world-to-camera.
        Ks: [C, 3, 3] pinhole intrinsics. near_plane, far_plane: depth culling. eps2d: low-pass added to the 2D
        covariance, in pixels^2. cpu_threads: host threads for CPU tensors, forward and backward (default: every
        usable core, or the limit of `threads.limited_host_threads` around the caller).

    Returns:
        means2d [C, N, 2] pixels, conics [C, N, 3] (upper triangle of the inverse 2D covariance), depths [C, N]
        camera z, radii [C, N] int32 (0 = culled). Culled entries of the float outputs are zero.
    """
    args = (means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d)
    if torch.is_grad_enabled() and any(t.requires_grad for t in (means, quats, scales, viewmats, Ks)):
        return _ProjectGaussians.apply(*args, cpu_threads)
    cams, n = viewmats.shape[0], means.shape[0]
    return _stage_forward(_PROJECTION, (cams, n), (cams, n), args, cpu_threads)


class _SHColors(torch.autograd.Function):
    """`spherical_harmonics` under autograd: the forward kernel as `_stage_forward` runs it, and the hand-written
    backward kernel (kernels/sh.py) over the same Gaussian ranges (`_backward_over_ranges`).

    The inputs and the colours (which tell the clamped channels) are kept with `save_for_backward`, so an in-place
    change to an input between forward and backward fails autograd's version check.
    """

    @staticmethod
    def forward(ctx, means, coeffs, viewmats, degree, cpu_threads):
        cams, n = viewmats.shape[0], means.shape[0]
        (colors,) = _stage_forward(_SH_COLORS, (cams, n), (cams, n), (means, coeffs, viewmats, degree), cpu_threads)
        ctx.save_for_backward(means, coeffs, viewmats, colors)
        ctx.degree, ctx.cpu_threads = degree, cpu_threads
        return colors

    @staticmethod
    def backward(ctx, v_colors):
        _first_derivatives_only("spherical_harmonics")
        means, coeffs, viewmats, colors = ctx.saved_tensors
        grads = _backward_over_ranges(
            _SH_COLORS, sh_to_colors_backward_kernel, gaussians=dict(means=means, coeffs=coeffs),
            cameras=dict(viewmats=viewmats), pairs=dict(colors=colors), cotangents=dict(colors=v_colors),
            cpu_threads=ctx.cpu_threads, degree=ctx.degree)
        grads = (grads["means"], grads["coeffs"], grads["viewmats"])
        return (*(g if needed else None for g, needed in zip(grads, ctx.needs_input_grad)), None, None)


def spherical_harmonics(means: torch.Tensor, coeffs: torch.Tensor, viewmats: torch.Tensor, degree: int,
                        cpu_threads: int | None = None) -> torch.Tensor:
    """View-dependent colour max(SH(dir) + 0.5, 0) with dir from each camera centre to each Gaussian.

    Args:
        means: [N, 3]. coeffs: [N, K, 3] with K >= (degree + 1)^2. viewmats: [C, 4, 4] world-to-camera.
        degree: active SH degree, 0-3.
        cpu_threads: host threads for CPU tensors, forward and backward (as `project_gaussians`).

    Returns:
        [C, N, 3] colours; differentiable in means, coeffs and viewmats (the coefficients above the degree get a
        zero gradient, and so do means and viewmats at degree 0).
    """
    if (not 0 <= degree <= 3 or coeffs.ndim != 3 or coeffs.shape[0] != means.shape[0]
            or coeffs.shape[1] < (degree + 1) ** 2 or coeffs.shape[2] != 3):
        # the kernel reads coefficients up to the degree's, one row per mean: fewer would be read past the tensor
        raise ValueError(f"spherical_harmonics of degree {degree} (0-3) needs coeffs [N = {means.shape[0]}, "
                         f"K >= {(degree + 1) ** 2}, 3], got {list(coeffs.shape)}")
    if torch.is_grad_enabled() and any(t.requires_grad for t in (means, coeffs, viewmats)):
        return _SHColors.apply(means, coeffs, viewmats, degree, cpu_threads)
    cams, n = viewmats.shape[0], means.shape[0]
    (colors,) = _stage_forward(_SH_COLORS, (cams, n), (cams, n), (means, coeffs, viewmats, degree), cpu_threads)
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
    # the kernels index Gaussians (cam * N + gaussian) and pixels (cam * H * W) in int32
    if cams * n >= INT32_LIMIT or cams * width * height >= INT32_LIMIT:
        raise ValueError(f"{cams} cameras x {n} Gaussians or x {width}x{height} pixels exceed int32 indices: render "
                         "fewer cameras per call")
    tiles = _tile_geometry(n, width, height, tile_size)
    num_tiles = cams * tiles.tiles_x * tiles.tiles_y
    splats = dict(means2d=_to_warp(means2d.detach().reshape(-1, 2).contiguous(), "vec2"),
                  conics=_to_warp(conics.detach().reshape(-1, 3).contiguous(), "vec3"),
                  opacities=_to_warp(opacities.detach().contiguous(), "scalar"),
                  radii=_to_warp(radii.reshape(-1).contiguous(), "int32"))
    if device.type == "cuda":
        tile_offsets, isect_ids = _bin_by_sort(splats, tiles, depths, num_tiles)
    else:
        tile_offsets, isect_ids = _bin_by_counting(splats, tiles, radii, depths, num_tiles,
                                                   cpu_threads or _default_cpu_threads())
    return TileBins(tile_size, tiles.tiles_x, tiles.tiles_y, tile_offsets, isect_ids)


def _tile_geometry(num_gaussians: int, width: int, height: int, tile_size: int) -> TileGeometry:
    """The kernels' `TileGeometry` of an image of width x height pixels in tiles of tile_size."""
    tiles = TileGeometry()
    tiles.num_gaussians, tiles.width, tiles.height, tiles.tile_size = num_gaussians, width, height, tile_size
    tiles.tiles_x, tiles.tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    return tiles


INT32_LIMIT = 2**31
"""Intersections, Gaussian and pixel indices are int32 in the kernels (as gsplat's): at this many they would wrap."""


def _check_intersections(count: int, what: str = "Gaussian-tile intersections") -> None:
    if count >= INT32_LIMIT:
        raise ValueError(f"{count} {what} exceed int32 offsets: render fewer cameras per call, fewer or smaller "
                         "Gaussians, or with a larger tile size")


def _bin_by_sort(splats: dict, tiles: TileGeometry, depths: torch.Tensor, num_tiles: int):
    """gsplat's binning: one (tile, depth) key per intersection, sorted (the GPU path)."""
    device = depths.device
    launcher = _launcher(device)
    counts = torch.empty(depths.numel(), dtype=torch.int32, device=device)
    launcher.launch(count_tiles_kernel, depths.numel(), **splats, tiles=tiles, tile_counts=_to_warp(counts, "int32"))
    ends = torch.cumsum(counts, 0, dtype=torch.int64)
    num_isects = int(ends[-1]) if ends.numel() else 0
    _check_intersections(num_isects)
    write_offsets = (ends - counts).to(torch.int32)
    # Culled Gaussians emit nothing, so every depth used here is > near_plane > 0, and a positive float32's bits
    # order as it does. float64 depths closer than a float32 step would tie there: their key is the Gaussian's rank
    # in its camera's depth order instead, the CPU path's order.
    if depths.dtype == torch.float32:
        depth_keys = depths.detach().reshape(-1).contiguous().view(torch.int32)
    else:
        order = torch.argsort(depths.detach(), dim=1, stable=True)
        ranks = torch.empty_like(order).scatter_(1, order, torch.arange(order.shape[1], device=device).expand_as(order))
        depth_keys = ranks.reshape(-1).to(torch.int32)
    keys = torch.empty(num_isects, dtype=torch.int64, device=device)
    ids = torch.empty(num_isects, dtype=torch.int32, device=device)
    if num_isects:
        launcher.launch(
            emit_intersections_kernel, depths.numel(), **splats, write_offsets=_to_warp(write_offsets, "int32"),
            depth_keys=_to_warp(depth_keys, "int32"), tiles=tiles, isect_keys=_to_warp(keys, "int64"),
            isect_ids=_to_warp(ids, "int32"),
        )
    keys, order = torch.sort(keys, stable=True)  # equal keys (float32 depth ties) in index order, as on the CPU
    tile_offsets = torch.searchsorted(keys >> 32, torch.arange(num_tiles + 1, device=device)).to(torch.int32)
    return tile_offsets, ids[order].contiguous()


def _bin_by_counting(splats: dict, tiles: TileGeometry, radii: torch.Tensor, depths: torch.Tensor, num_tiles: int,
                     threads: int):
    """Counting sort by tile of the depth-ordered Gaussians (the CPU path, kernels/bin.py). Every Gaussian's tile
    spans are found once, in parallel, and stored in depth order; then every camera's depth order, in chunks that
    are each a host-thread task with its own histogram and write cursors (Warp launches release the GIL), counts
    and fills the tiles from the spans. The lists are those of one serial walk."""
    cams, n = radii.shape
    launcher = _launcher(radii.device)
    tiles_per_camera = tiles.tiles_x * tiles.tiles_y
    depth_order = _to_warp(_depth_order(depths, radii).reshape(-1), "int32")
    first_rows = torch.empty(cams * n, dtype=torch.int32)
    row_counts = torch.empty(cams * n, dtype=torch.int32)
    launcher.launch(tile_rows_kernel, cams * n, means2d=splats["means2d"], radii=splats["radii"],
                    depth_order=depth_order, tiles=tiles, first_rows=_to_warp(first_rows, "int32"),
                    row_counts=_to_warp(row_counts, "int32"))
    row_ends = torch.cumsum(row_counts, 0, dtype=torch.int64)
    _check_intersections(int(row_ends[-1]) if len(row_ends) else 0, "rows of tiles met by Gaussians")
    row_ends = row_ends.to(torch.int32)
    spans = torch.empty(int(row_ends[-1]) if len(row_ends) else 0, 2, dtype=torch.int32)
    rows = dict(spans=wp.from_torch(spans, dtype=wp.vec2i), row_offsets=_to_warp(row_ends - row_counts, "int32"),
                first_rows=_to_warp(first_rows, "int32"), row_counts=_to_warp(row_counts, "int32"), tiles=tiles)

    def find_spans(_, first, stop):
        launcher.launch(tile_spans_kernel, stop - first, **splats, depth_order=depth_order, tiles=tiles,
                        row_offsets=rows["row_offsets"], first_rank=first, spans=rows["spans"])

    # more ranges than threads: the work per Gaussian varies
    _run_ranges(find_spans, _first_alone_then_equal(cams * n, 4 * threads), threads)

    chunks = _depth_chunks((radii > 0).sum(dim=1).tolist(), max(1, math.ceil(2 * threads / cams)) if threads > 1 else 1)
    cameras_of, starts, stops = (torch.tensor(column, dtype=torch.int32) for column in zip(*chunks))
    chunk_args = dict(**rows, chunk_starts=_to_warp(starts + cameras_of * n, "int32"),
                      chunk_stops=_to_warp(stops + cameras_of * n, "int32"))
    one_each = [(chunk, chunk + 1) for chunk in range(len(chunks))]
    counts = torch.zeros(len(chunks), tiles_per_camera, dtype=torch.int32)
    counts_wp = _to_warp(counts, "int32")

    def count(_, first, stop):
        launcher.launch(tile_histogram_kernel, stop - first, **chunk_args, first_chunk=first, chunk_counts=counts_wp)

    _run_ranges(count, one_each, threads)
    # Tile offsets over every camera's tiles; within a tile, each chunk writes after the camera's earlier chunks.
    camera_counts = torch.zeros(cams, tiles_per_camera, dtype=torch.int32).index_add_(0, cameras_of.long(), counts)
    _check_intersections(int(counts.sum(dtype=torch.int64)))
    tile_offsets = torch.zeros(num_tiles + 1, dtype=torch.int32)
    torch.cumsum(camera_counts.reshape(-1), 0, dtype=torch.int32, out=tile_offsets[1:])
    before = torch.zeros_like(counts)
    for cam in range(cams):
        of_camera = (cameras_of == cam).nonzero()[:, 0]
        before[of_camera] = torch.cumsum(counts[of_camera], 0, dtype=torch.int32) - counts[of_camera]
    cursors = before + tile_offsets[:-1].reshape(cams, tiles_per_camera)[cameras_of.long()]
    isect_ids = torch.empty(int(tile_offsets[-1]), dtype=torch.int32)
    cursors_wp, ids_wp = _to_warp(cursors.contiguous(), "int32"), _to_warp(isect_ids, "int32")

    def fill(_, first, stop):
        launcher.launch(fill_tiles_front_to_back_kernel, stop - first, **chunk_args, depth_order=depth_order,
                        first_chunk=first, chunk_cursors=cursors_wp, isect_ids=ids_wp)

    if len(isect_ids):
        _run_ranges(fill, one_each, threads)
    return tile_offsets, isect_ids


def _depth_order(depths: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """[C, N] int32: each camera's Gaussians front to back, culled ones last, equal depths in index order (so the
    lists are deterministic). float32 depths go through Warp's radix sort of (depth, index) pairs, which is stable:
    1.4 ms for 100k keys against 4.2-4.7 for numpy's sort of packed int64 keys and 10 for torch's stable argsort
    on one thread; float64 (the reference tests) keeps torch's stable argsort. The radix sort orders -0.0 before
    0.0 and NaN by its bits; neither reaches it, since the projection culls depths below the near plane."""
    keys = torch.where(radii > 0, depths.detach(), torch.full_like(depths, math.inf))
    if keys.dtype != torch.float32:
        return torch.argsort(keys, dim=1, stable=True).to(torch.int32)
    cams, n = keys.shape
    # radix_sort_pairs sorts in place and needs room for twice the pairs it sorts
    sort_keys = torch.empty(2 * n, dtype=torch.float32)
    order = torch.empty(cams, 2 * n, dtype=torch.int32)
    keys_wp = _to_warp(sort_keys, "scalar")
    for cam in range(cams):
        sort_keys[:n] = keys[cam]
        torch.arange(n, dtype=torch.int32, out=order[cam, :n])
        wp.utils.radix_sort_pairs(keys_wp, _to_warp(order[cam], "int32"), n)
    return order[:, :n]


def _depth_chunks(visible: list[int], per_camera: int) -> list[tuple[int, int, int]]:
    """(camera, start, stop) ranges of each camera's depth order over its `visible[camera]` unculled Gaussians: a
    one-Gaussian chunk first (`_run_ranges` runs the first range alone, for the kernels' first-use
    compilation), then `per_camera` equal chunks of the rest; empty ranges left out, at least one per camera."""
    chunks = []
    for cam, count in enumerate(visible):
        chunks += [(cam, a, b) for a, b in _first_alone_then_equal(count, per_camera)] or [(cam, 0, 0)]
    return chunks


def _points_by_cell(count_kernel, points: wp.array, grid, num_cells: int, device: torch.device
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Counting sort of `points` into the cells of `grid` (kernels/nearest.py's count and fill passes; `count_kernel`
    the grid's own count pass): ([num_cells + 1] int32 offsets, [P] int32 point indices), cell c's points at
    indices[offsets[c]:offsets[c + 1]]."""
    launcher = _launcher(device)
    point_cells = torch.empty(len(points), dtype=torch.int32, device=device)
    cell_counts = torch.zeros(num_cells, dtype=torch.int32, device=device)
    launcher.launch(count_kernel, len(points), points=points, grid=grid, point_cells=_to_warp(point_cells, "int32"),
                    cell_counts=_to_warp(cell_counts, "int32"))
    cell_offsets = torch.zeros(num_cells + 1, dtype=torch.int32, device=device)
    torch.cumsum(cell_counts, 0, dtype=torch.int32, out=cell_offsets[1:])
    cell_points = torch.empty(len(points), dtype=torch.int32, device=device)
    launcher.launch(fill_cells_kernel, len(points), point_cells=_to_warp(point_cells, "int32"),
                    cell_cursors=_to_warp(cell_offsets[:-1].clone(), "int32"),
                    cell_points=_to_warp(cell_points, "int32"))
    return cell_offsets, cell_points


# Points per grid cell the nearest-point search aims at: fewer cells cost the rings more points, more cells more
# empty cells to step over.
POINTS_PER_CELL = 4
MAX_GRID_CELLS_PER_AXIS = 1024
# How far past the queries' box, in multiples of its extent, the grid follows the points: a projection shifted off
# the mask keeps cells of its own (clamped into one border row, every query would scan all of it), while one far
# away, such as a point just in front of the camera, does not stretch the grid.
GRID_REACH = 2.0


@torch.no_grad()
def nearest_points(queries: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """[Q] int64: the index of the nearest of [P, 2] `points` to each of [Q, 2] `queries` (kernels/nearest.py).

    Exact (in the wider of the two dtypes), ties to the lowest index; points that are not finite are never
    nearest, and a query without a finite point gets -1. The grid spans the queries' bounding box, grown to hold
    the points up to `GRID_REACH` times the box's extent beyond it, in square cells that would hold
    `POINTS_PER_CELL` points each if the points were spread evenly over it.

    Raises:
        ValueError: a query is not finite.
    """
    device = points.device
    if len(queries) and not torch.isfinite(queries).all():
        raise ValueError("nearest_points: every query must be finite")
    if len(queries) == 0 or len(points) == 0:
        return torch.full((len(queries),), -1, dtype=torch.int64, device=device)
    dtype = torch.promote_types(queries.dtype, points.dtype)
    queries, points = queries.detach().to(dtype).contiguous(), points.detach().to(dtype).contiguous()
    low, high = queries.min(dim=0).values.double().cpu(), queries.max(dim=0).values.double().cpu()
    finite = points[torch.isfinite(points).all(dim=1)]
    if len(finite):
        reach = GRID_REACH * float((high - low).max())
        low = torch.minimum(low, finite.min(dim=0).values.double().cpu().clamp(min=low - reach))
        high = torch.maximum(high, finite.max(dim=0).values.double().cpu().clamp(max=high + reach))
    size = (high - low).clamp_min(1e-9)
    cell = max(math.sqrt(float(size[0] * size[1]) * POINTS_PER_CELL / len(points)),
               float(size.max()) / MAX_GRID_CELLS_PER_AXIS, 1e-9)
    grid = PointGrid()
    grid.origin = wp.vec2d(float(low[0]), float(low[1]))
    grid.cell = wp.float64(cell)
    grid.cells_x, grid.cells_y = (max(1, math.ceil(float(extent) / cell)) for extent in size)
    launcher = _launcher(device)
    query_array, point_array = _to_warp(queries, "vec2"), _to_warp(points, "vec2")
    cell_offsets, cell_points = _points_by_cell(count_cells_kernel, point_array, grid, grid.cells_x * grid.cells_y,
                                                device)
    nearest = torch.empty(len(queries), dtype=torch.int32, device=device)
    launcher.launch(nearest_in_grid_kernel, len(queries), queries=query_array, points=point_array, grid=grid,
                    cell_offsets=_to_warp(cell_offsets, "int32"), cell_points=_to_warp(cell_points, "int32"),
                    nearest=_to_warp(nearest, "int32"))
    return nearest.long()


# Points per cell of the k-nearest grid if they filled the box evenly; the box spans the points' 1st to 99th
# percentile per axis, widened by half its extent, so a few far floaters (clamped into the border cells) neither
# stretch the grid nor leave the object in a handful of cells. Gaussians lie on the object's surface, so most
# cells are empty: at 100k Gaussians and k = 316, 0.25 took 1.4-1.5 s, 2 took 2.0-2.1, 8 took 2.9, 32 took 4.0-4.3.
KNN_POINTS_PER_CELL = 0.25
KNN_BOX_QUANTILE = 0.01
KNN_MAX_CELLS_PER_AXIS = 256
# Queries per launch: each keeps its k nearest in a scratch row of k float64s (4096 x 316 neighbours: 10 MB), and a
# launch's rows stay within KNN_SCRATCH_BYTES for any k; many chunks, so that the host threads finish together.
KNN_CHUNK = 4096
KNN_SCRATCH_BYTES = 16 << 20


@torch.no_grad()
def mean_neighbour_distances(points: torch.Tensor, k: int) -> torch.Tensor:
    """[P] the mean Euclidean distance from each of [P, 3] `points` to its k nearest other points, in the points'
    dtype (kernels/knn.py; exact, measured in float64). Host threads over chunks of the points on the CPU.

    Points outside the grid's box (floaters) take every point in turn: 100k points on a sphere, k = 316, 1.3 s;
    with 1% of them scattered 300 radii out, 1.8 s (4.0 for scipy's k-d tree; 5.2 when they searched the grid
    shell by shell, as a review found). The slow case left is more than 1% of the points far away, which the box
    then takes in, leaving the object in a few cells: 10% on a shell 1000 radii out (not an object-centric scene)
    16.4 s against 3.6.

    Raises:
        ValueError: k is not in [1, P - 1], or a point is not finite.
    """
    count = len(points)
    if not 1 <= k < count:
        raise ValueError(f"mean_neighbour_distances: k must be in [1, {count - 1}] for {count} points, got {k}")
    if not torch.isfinite(points).all():
        raise ValueError("mean_neighbour_distances: every point must be finite")
    device = points.device
    points = points.detach().contiguous()
    coordinates = points.double()
    # order statistics by kthvalue: torch.quantile refuses inputs of more than 16M values
    low = coordinates.kthvalue(1 + int(KNN_BOX_QUANTILE * (count - 1)), dim=0).values.cpu()
    high = coordinates.kthvalue(count - int(KNN_BOX_QUANTILE * (count - 1)), dim=0).values.cpu()
    margin = 0.5 * (high - low)
    low, high = low - margin, high + margin
    size = (high - low).clamp_min(1e-9)
    cell = max(float(size.prod() * KNN_POINTS_PER_CELL / count) ** (1 / 3),
               float(size.max()) / KNN_MAX_CELLS_PER_AXIS, 1e-9)
    grid = PointGrid3()
    grid.origin = wp.vec3d(*(float(v) for v in low))
    grid.cell = wp.float64(cell)
    grid.cells_x, grid.cells_y, grid.cells_z = (max(1, math.ceil(float(extent) / cell)) for extent in size)
    launcher = _launcher(device)
    point_array = _to_warp(points, "vec3")
    cell_offsets, cell_points = _points_by_cell(count_cells_3d_kernel, point_array, grid,
                                                grid.cells_x * grid.cells_y * grid.cells_z, device)
    means = torch.empty(count, dtype=torch.float64, device=device)
    arguments = dict(points=point_array, grid=grid, cell_offsets=_to_warp(cell_offsets, "int32"),
                     cell_points=_to_warp(cell_points, "int32"), k=k, mean_distances=_to_warp(means, "scalar"))

    def work(_, start, stop):
        heaps = torch.empty(stop - start, k, dtype=torch.float64, device=device)
        launcher.launch(mean_knn_distance_kernel, stop - start, **arguments, first_point=start,
                        heaps=wp.from_torch(heaps, dtype=wp.float64))

    chunk = max(1, min(KNN_CHUNK, KNN_SCRATCH_BYTES // (8 * k)))
    workers = 1 if device.type == "cuda" else _default_cpu_threads()
    _run_ranges(work, _first_alone_then_chunks(count, chunk), workers)
    return means.to(points.dtype)


# Rays per host-thread range of the coherence search: ~1500 mask pixels per view, so a few ranges per view and
# enough of them that two threads finish together.
COHERENCE_RAYS_PER_RANGE = 512


@torch.no_grad()
def least_outside_samples(rays: torch.Tensor, ray_views: torch.Tensor, origins: torch.Tensor, depths: torch.Tensor,
                          viewmats: torch.Tensor, Ks: torch.Tensor, distances: torch.Tensor, margin: float,
                          size: float) -> torch.Tensor:
    """[R] int64: for each ray, the index of the depth sample nearest to passing through every other view's mask
    (kernels/coherence.py; the search of `SilhouetteTargets.coherence_loss`). Host threads over ranges of rays on
    the CPU.

    Args:
        rays: [R, 3] world directions at unit depth. ray_views: [R] the view each ray leaves from.
        origins: [C, 3] camera centres. depths: [C, S] each view's sample depths along its rays.
        viewmats: [C, 4, 4] world-to-camera. Ks: [C, 3, 3].
        distances: [C, H + 2 margin, W + 2 margin] distance transforms outside the masks (image sizes).
        margin: pixels of continued mask around each image. size: the image size the distances are measured in.
    """
    device = rays.device
    count = len(rays)
    least = torch.empty(count, dtype=torch.int32, device=device)
    if count == 0:
        return least.long()
    dtype = rays.dtype
    scalar = _WP_SCALARS[dtype]
    intrinsics = torch.stack([Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2]], dim=-1).to(dtype).contiguous()
    launcher = _launcher(device)
    arguments = dict(origins=_to_warp(origins.to(dtype).contiguous(), "vec3"),
                     depths=_to_warp(depths.to(dtype).contiguous(), "scalar"),
                     viewmats=_to_warp(viewmats.to(dtype).contiguous(), "mat44"),
                     intrinsics=_to_warp(intrinsics, "vec4"),
                     distances=_to_warp(distances.float().contiguous(), "scalar"),
                     margin=scalar(margin), size=scalar(size))
    rays, ray_views = rays.contiguous(), ray_views.to(torch.int32).contiguous()

    def work(_, start, stop):
        launcher.launch(least_outside_sample_kernel, stop - start, **arguments, rays=_to_warp(rays[start:stop], "vec3"),
                        ray_views=_to_warp(ray_views[start:stop], "int32"), least=_to_warp(least[start:stop], "int32"))

    if device.type == "cuda":
        work(0, 0, count)
    else:
        _run_ranges(work, _first_alone_then_chunks(count, COHERENCE_RAYS_PER_RANGE), _default_cpu_threads())
    return least.long()


@functools.lru_cache(maxsize=8)
def ssim_window(device: str, dtype: torch.dtype) -> torch.Tensor:
    """SSIM's 1-D Gaussian window (11 taps, sigma 1.5), the one kernels/loss.py's row and column passes apply."""
    return gaussian_taps(WINDOW_RADIUS, SSIM_SIGMA, dtype, device)


def _row_passes(kernel, before: list, after: list, rows: int, runs: int, device: torch.device) -> None:
    """Launch a pass of kernels/loss.py (arguments `before`, the launch's first row, `after`) over `rows` image rows
    of `runs` runs each, split into row ranges across host threads on the CPU. The pass is complete when this
    returns: the next one reads neighbouring rows."""
    workers = 1 if device.type == "cuda" else min(_default_cpu_threads(), max(rows // 16, 1))
    ranges = _first_alone_then_equal(rows, 2 * workers)
    launcher = _launcher(device)  # every launch names its device and stream: no process-wide default

    def work(_, first, stop):  # positional arguments (split around the first row), otherwise as `_Launcher.launch`
        wp.launch(kernel, dim=(runs, stop - first), inputs=[*before, first, *after],
                  device=launcher.device, stream=launcher.stream, record_tape=False)

    _run_ranges(work, ranges, workers)


def _runs(planes: torch.Tensor) -> wp.array:
    """Warp view of contiguous [..., RUN] planes as an array of RUN-vectors."""
    return _to_warp(planes.view(-1, RUN), f"vec{RUN}")


class _FusedPhotometricLoss(torch.autograd.Function):
    """(loss, L1, SSIM) of [B, H, W, 3] images against targets; only the loss is differentiable (in the images).
    The passes and their planes (per channel, rows padded to runs of RUN pixels): kernels/loss.py."""

    @staticmethod
    def forward(ctx, images, targets, lambda_dssim):
        batch, height, width, _ = images.shape
        images, targets = images.detach().contiguous(), targets.to(images.dtype).contiguous()
        rows, runs = batch * height, -(-width // RUN)
        window = _to_warp(ssim_window(str(images.device), images.dtype), "scalar")
        # x's and y's channel planes, each row with a zero run before and after it (the row blur's zero padding)
        planes = images.new_zeros(6, rows, runs + 2, RUN)
        planes.view(6, batch, height, -1)[:3, ..., RUN:RUN + width] = images.permute(3, 0, 1, 2)
        planes.view(6, batch, height, -1)[3:, ..., RUN:RUN + width] = targets.permute(3, 0, 1, 2)
        row_means = images.new_empty(15, rows, runs, RUN)
        _row_passes(ssim_row_pass_kernel, [_runs(planes), window, rows, runs], [_runs(row_means)], rows, runs,
                    images.device)
        ssim_sums = images.new_empty(rows * runs)
        l1_sums = torch.empty_like(ssim_sums)
        partials = images.new_empty(9, rows, runs + 2, RUN)  # dS/dmu_x, dS/dE[x^2], dS/dE[xy] per channel
        partials[:, :, [0, -1]] = 0  # the padding runs, for the backward's row blur
        _row_passes(ssim_column_pass_kernel, [_runs(planes), window, width, height, rows, runs],
                    [_runs(row_means), _to_warp(ssim_sums, "scalar"), _to_warp(l1_sums, "scalar"), _runs(partials)],
                    rows, runs, images.device)
        values = 3 * batch * height * width
        l1, ssim_value = l1_sums.sum() / values, ssim_sums.sum() / values
        loss = (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim_value)
        ctx.save_for_backward(planes, partials)
        ctx.shape = images.shape
        ctx.lambda_dssim = lambda_dssim
        ctx.mark_non_differentiable(l1, ssim_value)
        return loss, l1, ssim_value

    @staticmethod
    def backward(ctx, v_loss, _v_l1, _v_ssim):
        _first_derivatives_only("fused_photometric_loss")
        planes, partials = ctx.saved_tensors
        batch, height, width, _ = ctx.shape
        rows, runs = batch * height, -(-width // RUN)
        window = _to_warp(ssim_window(str(planes.device), planes.dtype), "scalar")
        blurred = planes.new_empty(9, rows, runs, RUN)
        _row_passes(ssim_grad_row_pass_kernel, [window, rows, runs], [_runs(partials), _runs(blurred)], rows, runs,
                    planes.device)
        v_planes = planes.new_empty(3, rows, runs, RUN)
        scalar = _WP_SCALARS[planes.dtype]
        values = 3 * batch * height * width
        scales = [scalar(-ctx.lambda_dssim / values), scalar((1 - ctx.lambda_dssim) / values)]
        _row_passes(photometric_grad_kernel, [_runs(planes), window, height, rows, runs],
                    [_runs(blurred), *scales, _runs(v_planes)], rows, runs, planes.device)
        v_images = v_planes.view(3, batch, height, runs * RUN)[..., :width].permute(1, 2, 3, 0)
        return v_images * v_loss, None, None


def fused_photometric_loss(images: torch.Tensor, targets: torch.Tensor, lambda_dssim: float
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(loss, L1, SSIM) of [B, H, W, 3] `images` against `targets` (no gradient), loss = (1 - lambda_dssim) L1 +
    lambda_dssim (1 - SSIM) with SSIM's 11 x 11 Gaussian window (sigma 1.5) zero-padded: the passes of
    kernels/loss.py, split over host threads on the CPU. Only the loss is differentiable, in the images."""
    return _FusedPhotometricLoss.apply(images, targets, lambda_dssim)


def _default_cpu_threads() -> int:
    """Host threads for CPU launches when the caller names none: every usable core, or the limit around the
    caller (`threads.limited_host_threads`)."""
    return host_threads()


def _cost_balanced_ranges(tile_costs: torch.Tensor, items_per_tile: int, parts: int) -> list[tuple[int, int]]:
    """Split the tile-major index space (pixels or pixel blocks, `items_per_tile` per tile) into tile-aligned
    [start, stop) ranges: the first tile alone (it runs before the threads start, see `_run_ranges`), then up to
    `parts` contiguous ranges of about equal total cost over the rest (`tile_costs`: [tiles], e.g. list lengths)."""
    num_tiles = tile_costs.numel()
    if num_tiles == 0:
        return []
    # cumulative[c]: the cost of the first c tiles after the first one
    cumulative = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(tile_costs[1:].double(), 0)])
    total = float(cumulative[-1])
    if total > 0:
        # each cut after the tile count whose running cost is nearest to i / parts of the total
        targets = torch.arange(1, parts, dtype=torch.float64) * (total / parts)
        above = torch.searchsorted(cumulative, targets).clamp(max=len(cumulative) - 1)
        below = (above - 1).clamp(min=0)
        nearer_below = (targets - cumulative[below]) < (cumulative[above] - targets)
        cuts = (1 + torch.where(nearer_below, below, above)).tolist()
    else:
        cuts = torch.linspace(1, num_tiles, parts + 1)[1:-1].round().long().tolist()
    bounds = [1, *cuts, num_tiles]
    tiles = [(0, 1)] + [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    return [(a * items_per_tile, b * items_per_tile) for a, b in tiles]


def _raster_ranges(num_tiles: int, blocks_per_tile: int, workers: int, parts_per_worker: int,
                   tile_costs) -> list[tuple[int, int]]:
    """The rasterizer's block ranges: one over every tile for one worker (CUDA; no costs read back), else
    `parts_per_worker` cost-balanced ranges per worker after the first tile (`tile_costs()`: [tiles] costs)."""
    if workers == 1:
        return [(0, num_tiles * blocks_per_tile)] if num_tiles else []
    return _cost_balanced_ranges(tile_costs().cpu(), blocks_per_tile, parts_per_worker * workers)


def _run_ranges(work, ranges: list[tuple[int, int]], workers: int) -> None:
    """Run work(i, start, stop) for every range i, on `workers` host threads that each take the next range when
    they are free (dynamic scheduling: a static share left one thread idle while the other binned every camera).

    Warp CPU launches release the GIL, so host threads over disjoint ranges run in parallel. The first range runs
    alone on the calling thread, so that a kernel's first-use compilation happens once, not in every thread at the
    same time. Whatever `work` writes must depend on its range i only, never on the thread that ran it (per-range
    outputs or gradient buffers): then results are the same bit for bit for every schedule.
    """
    if not ranges:
        return
    work(0, *ranges[0])
    if workers <= 1 or len(ranges) <= 2:
        for i in range(1, len(ranges)):
            work(i, *ranges[i])
        return
    list(thread_pool("warpbags", workers).map(lambda i: work(i, *ranges[i]), range(1, len(ranges))))


def _visits_per_tile(tile_offsets: torch.Tensor, isect_end: torch.Tensor, tiles: TileGeometry) -> torch.Tensor:
    """[tiles] the list entries the forward composited, summed over each tile's pixels (isect_end: [C, H, W]):
    the work of the backward, which walks each pixel's contributing range back to front. Summed over tiles as a
    reshape of the image padded to whole tiles (a gather and scatter per pixel cost 3x as much)."""
    cams, height, width = isect_end.shape
    size, tiles_x, tiles_y = tiles.tile_size, tiles.tiles_x, tiles.tiles_y
    ends = F.pad(isect_end.to(device="cpu", dtype=torch.int64), (0, tiles_x * size - width, 0, tiles_y * size - height))
    ends_per_tile = ends.view(cams, tiles_y, size, tiles_x, size).sum(dim=(2, 4))
    rows = (height - torch.arange(tiles_y) * size).clamp(max=size)
    columns = (width - torch.arange(tiles_x) * size).clamp(max=size)
    starts = tile_offsets[:-1].to(device="cpu", dtype=torch.int64).view(cams, tiles_y, tiles_x)
    return (ends_per_tile - rows[:, None] * columns[None, :] * starts).reshape(-1) + 1


# Pixels one rasterizer thread composites, (width, height) within a tile. On CUDA one pixel per thread (gsplat's
# layout: threads are cheap, registers are not). On the CPU a thread walks its tile's list once for a block of
# pixels, so each Gaussian's loads (and the gradient adds of the backward) serve every pixel of the block.
# The lanes of a block run the same branch-free arithmetic, so the compiler vectorizes them: larger blocks pay.
# Measured on a quiet machine (2026-12-02, `python bench/train_step.py --inits random --views 1 --warmup 30
# --steps 20 --pixel-blocks 4x1,4x2,4x4`: maryrose 432^2, 10k random-init Gaussians, 174 visits per pixel; wall ms
# of raster forward / backward / whole step): 4x1 173 / 316 / 478, 4x2 129 / 253 / 395, 4x4 92 / 224 / 335; and
# `python bench/rasterize.py --sizes 128,432 --gaussians 10000 --cameras 4,1 --blocks 4x1,4x2,4x4` (forward +
# backward, 128^2 / 4 cameras): 62.6 / 55.6 / 52.3.
# 4x4 is one block per tile at the CPU's 4-pixel tiles (`pixel_block_for` shrinks it where the tile is smaller).
DEFAULT_PIXEL_BLOCK: dict[str, tuple[int, int]] = {"cuda": (1, 1), "cpu": (4, 4)}


def pixel_block_for(device: torch.device, tile_size: int, block: tuple[int, int] | None) -> tuple[int, int]:
    """The pixel block the rasterizer runs for `block` (None: the device's default) on tiles of `tile_size` px: each
    side the largest power of two that divides the tile size and is not above the asked side (a block never spans two
    tiles, and a tile of 6 or 18 px gets 2 px sides, not 3: the kernels are built for power-of-two pixel counts).
    The benches check with it that the block a column names is the one that ran.

    Raises:
        ValueError: more pixels per thread than the rasterizer has kernels for.
    """
    block_w, block_h = block or DEFAULT_PIXEL_BLOCK["cuda" if device.type == "cuda" else "cpu"]
    block_w, block_h = (max(d for d in (1, 2, 4, 8, 16) if d <= max(side, 1) and tile_size % d == 0)
                        for side in (block_w, block_h))
    if block_w * block_h not in FORWARD_KERNELS:
        raise ValueError(f"pixel block {block_w}x{block_h}: the rasterizer is built for {sorted(FORWARD_KERNELS)} pixels per thread")
    return block_w, block_h


# Per-Gaussian rasterizer inputs (flattened over cameras) and their kinds; the backward kernel's gradient outputs
# carry the same names with a "v_" prefix.
_SPLAT_KINDS = {"means2d": "vec2", "conics": "vec3", "colors": "vec3", "opacities": "scalar", "depths": "scalar"}


def _flat_splats(means2d, conics, colors, opacities, depths) -> dict[str, torch.Tensor]:
    """The rasterizer's per-Gaussian inputs, detached, flattened over cameras and contiguous."""
    return dict(means2d=means2d.detach().reshape(-1, 2).contiguous(),
                conics=conics.detach().reshape(-1, 3).contiguous(),
                colors=colors.detach().reshape(-1, 3).contiguous(),
                opacities=opacities.detach().contiguous(),
                depths=depths.detach().reshape(-1).contiguous())


def _splat_arguments(splats: dict[str, torch.Tensor], tile_offsets: torch.Tensor, isect_ids: torch.Tensor,
                     geometry: dict) -> dict:
    """The arguments both rasterizer kernels start with: the splats, the tile bins, the `TileGeometry` and the
    pixel block."""
    return {**{name: _to_warp(t, _SPLAT_KINDS[name]) for name, t in splats.items()},
            "tile_offsets": _to_warp(tile_offsets, "int32"), "isect_ids": _to_warp(isect_ids, "int32"), **geometry}


_FLOAT32_EXACT_COUNT = 2**24  # integers from here on are not all representable in float32


class _RasterizeToPixels(torch.autograd.Function):
    """Forward and hand-written backward rasterization kernels; see kernels/rasterize.py.

    The inputs and the bins are kept with `save_for_backward`, so an in-place change to one of them between forward
    and backward fails autograd's version check.
    """

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, bins: TileBins, width, height, cpu_threads,
                pixel_block):
        cams, n = depths.shape
        device, scalar = means2d.device, means2d.dtype
        if scalar == torch.float32 and n >= _FLOAT32_EXACT_COUNT:
            # the kernels count a pixel's position in its tile's list (at most n entries) in the float type
            raise ValueError(f"float32 rasterization takes fewer than 2^24 Gaussians per camera, got {n}")
        splats = _flat_splats(means2d, conics, colors, opacities, depths)
        pixels = cams * height * width
        out_colors = torch.zeros(cams, height, width, 3, dtype=scalar, device=device)
        out_depths = torch.zeros(cams, height, width, dtype=scalar, device=device)
        out_alphas = torch.zeros(cams, height, width, dtype=scalar, device=device)
        final_transmittance = torch.ones(cams, height, width, dtype=scalar, device=device)
        isect_end = torch.zeros(cams, height, width, dtype=torch.int32, device=device)

        outputs = dict(
            out_colors=_to_warp(out_colors.view(pixels, 3), "vec3"),
            out_depths=_to_warp(out_depths.view(pixels), "scalar"),
            out_alphas=_to_warp(out_alphas.view(pixels), "scalar"),
            final_transmittance=_to_warp(final_transmittance.view(pixels), "scalar"),
            isect_end=_to_warp(isect_end.view(pixels), "int32"),
        )
        workers = 1 if device.type == "cuda" else (cpu_threads or _default_cpu_threads())
        block_w, block_h = pixel_block_for(device, bins.tile_size, pixel_block)
        ctx.lanes = block_w * block_h
        ctx.geometry = dict(tiles=_tile_geometry(n, width, height, bins.tile_size), block_w=block_w, block_h=block_h)
        common = _splat_arguments(splats, bins.tile_offsets, bins.isect_ids, ctx.geometry)
        blocks_per_tile = bins.tile_size**2 // ctx.lanes
        # a tile's cost: its list, walked once per block (less where its pixels saturate early)
        ranges = _raster_ranges(cams * bins.tiles_x * bins.tiles_y, blocks_per_tile, workers, 4,
                                lambda: torch.diff(bins.tile_offsets) + 1)
        kernel = FORWARD_KERNELS[ctx.lanes]
        launcher = _launcher(device)

        def work(_, start, stop):
            launcher.launch(kernel, stop - start, **common, first_block=start, **outputs)

        _run_ranges(work, ranges, workers)

        ctx.workers, ctx.blocks_per_tile = workers, blocks_per_tile
        ctx.save_for_backward(means2d, conics, colors, opacities, depths, bins.tile_offsets, bins.isect_ids,
                              final_transmittance, isect_end)
        ctx.mark_non_differentiable(final_transmittance, isect_end)
        # an output the loss does not use gets None, not zeros: without a depth loss the backward skips the depth terms
        ctx.set_materialize_grads(False)
        return out_colors, out_depths, out_alphas, final_transmittance, isect_end

    @staticmethod
    def backward(ctx, v_out_colors, v_out_depths, v_out_alphas, _v_transmittance, _v_isect_end):
        _first_derivatives_only("rasterize_to_pixels")
        *inputs, tile_offsets, isect_ids, final_transmittance, isect_end = ctx.saved_tensors
        splats = _flat_splats(*inputs)
        workers = ctx.workers
        pixels = final_transmittance.numel()
        device, scalar = final_transmittance.device, final_transmittance.dtype

        def cotangent(v, *shape):
            if v is None:
                return torch.zeros(*shape, dtype=scalar, device=device)
            return v.contiguous().view(*shape)

        common = _splat_arguments(splats, tile_offsets, isect_ids, ctx.geometry)
        saved = dict(
            final_transmittance=_to_warp(final_transmittance.view(pixels), "scalar"),
            isect_end=_to_warp(isect_end.view(pixels), "int32"),
            v_out_colors=_to_warp(cotangent(v_out_colors, pixels, 3), "vec3"),
            v_out_depths=_to_warp(cotangent(v_out_depths, pixels), "scalar"),
            v_out_alphas=_to_warp(cotangent(v_out_alphas, pixels), "scalar"),
        )
        # Two ranges per worker, balanced by the forward's exact visits. Each range costs a buffer set (a zero fill
        # and a sum of every splat gradient, ~1 ms at 100k Gaussians), but one range per worker left a thread idle
        # for a tenth of the backward (79.5 against 91.4 ms at 100k): a paper-preset step at 100k Gaussians took
        # 194 / 188 ms with two per worker, 200 / 197 with one, 197 with three (`bench/run_steps.py`, alternating).
        ranges = _raster_ranges(tile_offsets.numel() - 1, ctx.blocks_per_tile, workers, 2,
                                lambda: _visits_per_tile(tile_offsets, isect_end, ctx.geometry["tiles"]))
        # One private set of gradient buffers per range (CPU atomics are plain adds), summed in range order: the
        # gradients do not depend on which thread ran which range. The first range, which runs alone before the
        # others start, shares the second one's set.
        # Each set but the shared one is zeroed by its range, on its worker thread (torch releases the GIL): at 100k
        # Gaussians a set is ~1M floats, and zeroing them all up front kept one core idle.
        buffers = [{name: (torch.zeros_like if set_ == 0 else torch.empty_like)(t) for name, t in splats.items()}
                   for set_ in range(max(len(ranges) - 1, 1))]
        wp_buffers = [{"v_" + name: _to_warp(t, _SPLAT_KINDS[name]) for name, t in b.items()} for b in buffers]

        kernel = BACKWARD_KERNELS[ctx.lanes, v_out_depths is not None]
        launcher = _launcher(device)

        def work(i, start, stop):
            if i >= 2:
                for buffer in buffers[i - 1].values():
                    buffer.zero_()
            launcher.launch(kernel, stop - start, **common, first_block=start, **saved, **wp_buffers[max(i - 1, 0)])

        _run_ranges(work, ranges, workers)

        # summed into the first set in range order, in place
        for later in buffers[1:]:
            for name, buffer in later.items():
                buffers[0][name].add_(buffer)
        v_means2d, v_conics, v_colors, v_opacities, v_depths = buffers[0].values()
        cams, n = final_transmittance.shape[0], ctx.geometry["tiles"].num_gaussians
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
