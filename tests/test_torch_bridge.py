"""The torch bridge (warpbags/wrapper.py): what it builds with and without gradients, autograd's version check on
its saved inputs, the device every launch names, and the pose transform against warpbags.lie's torch maps."""

from __future__ import annotations

import contextlib
import gc
import math
import weakref

import pytest
import torch
import warp as wp
from conftest import DEVICES, random_scene
from random_poses import generator, random_viewmats

import warpbags
from warpbags import wrapper
from warpbags.lie import se3_exp
from warpbags.losses import photometric_loss
from warpbags.wrapper import apply_object_deltas, apply_pose_deltas

DIFFERENTIABLE = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "pose_deltas")


def _leaves(device="cpu", sh_degree=None, dtype=torch.float64):
    scene = random_scene(n=40, cams=2, width=20, height=16, sh_degree=sh_degree, dtype=dtype, seed=4, device=device)
    width, height = scene.pop("width"), scene.pop("height")
    scene["pose_deltas"] = 0.01 * torch.ones(2, 6, dtype=dtype, device=device)
    return {k: v.clone().requires_grad_() for k, v in scene.items()}, width, height


@pytest.fixture
def recorder(monkeypatch):
    """Counts Warp Tapes, Warp arrays created with an adjoint buffer, and every wp.launch's keyword arguments (a CUDA
    launch without a stream argument is recorded with the stream it ran on)."""
    record = {"tapes": 0, "adjoint_buffers": 0, "launches": []}
    real_tape, real_from_torch, real_launch = wp.Tape, wp.from_torch, wp.launch

    def tape(*args, **kwargs):
        record["tapes"] += 1
        return real_tape(*args, **kwargs)

    def from_torch(tensor, *args, **kwargs):
        if kwargs.get("requires_grad") or kwargs.get("grad") is not None:
            record["adjoint_buffers"] += 1
        return real_from_torch(tensor, *args, **kwargs)

    def launch(kernel, *args, **kwargs):
        device = kwargs.get("device")
        if kwargs.get("stream") is None and device is not None and wp.get_device(device).is_cuda:
            kwargs_seen = {**kwargs, "stream": wp.get_stream(device)}  # a Tape's replay: the device's current stream
        else:
            kwargs_seen = kwargs
        record["launches"].append((kernel.key, kwargs_seen))
        return real_launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "Tape", tape)
    monkeypatch.setattr(wp, "from_torch", from_torch)
    monkeypatch.setattr(wp, "launch", launch)
    return record


@pytest.mark.parametrize("sh_degree", [None, 1])
def test_forward_without_gradients_builds_no_tape_and_no_adjoint_buffers(recorder, sh_degree):
    leaves, width, height = _leaves(sh_degree=sh_degree)
    with torch.no_grad():
        out, alpha, meta = warpbags.rasterization(**leaves, width=width, height=height, sh_degree=sh_degree)
    assert recorder["launches"], "the render ran"
    assert recorder["tapes"] == 0 and recorder["adjoint_buffers"] == 0
    assert out.grad_fn is None and meta["viewmats"].grad_fn is None and meta["means2d"].grad_fn is None
    assert not any(kwargs.get("adjoint") for _, kwargs in recorder["launches"])

    # The same render with gradients: the backward pass records a Warp Tape for the pose stage, the one stage
    # differentiated by Warp, makes its adjoint buffers and runs the Tape; the projection, SH (with coefficients)
    # and the rasterizer launch their hand-written backward kernels.
    grad_out, _, _ = warpbags.rasterization(**leaves, width=width, height=height, sh_degree=sh_degree)
    torch.testing.assert_close(grad_out, out, rtol=0, atol=0)
    assert recorder["tapes"] == 0 and recorder["adjoint_buffers"] == 0
    assert not any(kwargs.get("adjoint") for _, kwargs in recorder["launches"])
    backward_kernels = {wrapper.project_gaussians_backward_kernel.key}
    if sh_degree is not None:
        backward_kernels.add(wrapper.sh_to_colors_backward_kernel.key)
    assert not backward_kernels & {key for key, _ in recorder["launches"]}
    grad_out.sum().backward()
    adjoints = {key for key, kwargs in recorder["launches"] if kwargs.get("adjoint")}
    assert adjoints == {wrapper.apply_pose_deltas_kernel.key}
    assert backward_kernels <= {key for key, _ in recorder["launches"]}
    assert recorder["tapes"] == 1 and recorder["adjoint_buffers"] > 0
    assert all(leaves[name].grad is not None for name in DIFFERENTIABLE)


@pytest.mark.parametrize("sh_degree", [None, 1])
def test_a_step_frees_its_stage_outputs(sh_degree):
    """Nothing outlives a forward + backward: a stage output held by its own autograd node (through a Warp view
    of it kept for the backward) is a cycle Python's collector cannot free, and it leaked every training step's
    buffers (about 2 MB per step at 432^2)."""
    leaves, width, height = _leaves(sh_degree=sh_degree)
    out, alpha, meta = warpbags.rasterization(**leaves, width=width, height=height, sh_degree=sh_degree)
    (out.sum() + alpha.sum()).backward()
    outputs = [weakref.ref(meta[name]) for name in ("means2d", "conics", "viewmats")]
    del out, alpha, meta
    gc.collect()
    assert all(output() is None for output in outputs)


def test_pose_stage_without_gradients_in_inference_mode(recorder):
    viewmats = random_viewmats(3, generator(1)).requires_grad_()
    deltas = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    with torch.inference_mode():
        out = apply_pose_deltas(viewmats, deltas)
    assert recorder["adjoint_buffers"] == 0 and out.grad_fn is None
    torch.testing.assert_close(out, viewmats.detach(), rtol=0, atol=1e-15)


@pytest.mark.parametrize("name", DIFFERENTIABLE)
@pytest.mark.parametrize("sh_degree", [None, 1])
def test_in_place_edit_between_forward_and_backward_fails_the_version_check(name, sh_degree):
    leaves, width, height = _leaves(sh_degree=sh_degree)
    out, alpha, _ = warpbags.rasterization(**leaves, width=width, height=height, sh_degree=sh_degree)
    with torch.no_grad():
        leaves[name].add_(1e-3)  # as an optimizer step between forward and backward would
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        (out.sum() + alpha.sum()).backward()


@pytest.mark.parametrize("name", ["viewmats", "params", "object_centers"])
def test_in_place_edit_of_an_object_delta_input_fails_the_version_check(name):
    inputs = dict(viewmats=random_viewmats(3, generator(2)), params=0.01 * torch.ones(3, 6, dtype=torch.float64),
                  object_centers=torch.zeros(3, 3, dtype=torch.float64))
    inputs = {k: v.clone().requires_grad_() for k, v in inputs.items()}
    out = apply_object_deltas(**inputs)
    with torch.no_grad():
        inputs[name].add_(1e-3)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.sum().backward()


@pytest.mark.parametrize("device", DEVICES)
def test_every_launch_names_its_device_and_stream_from_worker_threads(recorder, monkeypatch, device):
    """No launch relies on Warp's process-wide default device, and no ScopedDevice is entered, even with the CPU
    path's host threads (renderer and fused loss); on CUDA every launch is on torch's current stream."""

    def no_scoped_device(*args, **kwargs):
        raise AssertionError("wp.ScopedDevice changes the default device of every thread")

    monkeypatch.setattr(wp, "ScopedDevice", no_scoped_device)
    leaves, width, height = _leaves(device=device, sh_degree=1)
    stream = torch.cuda.Stream(device) if device == "cuda" else None
    if stream is not None:
        stream.wait_stream(torch.cuda.current_stream(device))  # the inputs were written on the default stream
    with torch.cuda.stream(stream) if stream is not None else contextlib.nullcontext():
        out, alpha, _ = warpbags.rasterization(**leaves, width=width, height=height, sh_degree=1, cpu_threads=2)
        loss, _ = photometric_loss(out, torch.rand_like(out).detach())  # the fused L1 + SSIM passes, threaded too
        (loss + out.sum() + alpha.sum()).backward()
    launches = recorder["launches"]
    assert any(kwargs.get("adjoint") for _, kwargs in launches), "the backward launched Warp adjoints"
    expected = wp.device_from_torch(leaves["means"].device)  # "cuda:0": Warp 1.19 cannot map an index-less "cuda"
    for key, kwargs in launches:
        assert kwargs.get("device") == expected, key
        if stream is None:
            assert kwargs.get("stream") is None, key
        else:
            assert kwargs["stream"].cuda_stream == stream.cuda_stream, key


def test_launch_arguments_are_checked_by_name():
    launcher = wrapper._launcher(torch.device("cpu"))
    with pytest.raises(TypeError, match="missing arguments \\['pose_deltas', 'out_viewmats'\\]"):
        launcher.launch(wrapper.apply_pose_deltas_kernel, 1, viewmats=None)
    with pytest.raises(TypeError, match="declared"):
        wrapper._stage(wrapper.apply_pose_deltas_kernel, {"out_viewmats": "mat44"}, pose_deltas="scalar",
                       viewmats="mat44")


# The pose transform has one implementation on the render path (the Warp kernel behind apply_pose_deltas, series
# below theta^2 = 0.04); warpbags.lie.se3_exp is its closed-form torch counterpart (series below theta^2 = 0.25),
# public for library users. They must agree at and near zero, where every camera starts, and across both cut-offs.
ANGLES = [0.0, 1e-12, 1e-8, 1e-6, 1e-4, 1e-2, 0.1, 0.2 - 1e-7, 0.2, 0.2 + 1e-7, 0.3, 0.5 - 1e-7, 0.5 + 1e-7, 1.0]


# Measured largest differences: float64 1.9e-15 (values) and 1.5e-14 (gradients, which reach 12.6), just below the
# Warp series' cut-off; float32 4.8e-7 and 9.5e-7, a few units in the last place.
@pytest.mark.parametrize("dtype,value_tol,grad_tol", [(torch.float64, 1e-14, 5e-14), (torch.float32, 2e-6, 5e-6)])
def test_warp_pose_transform_agrees_with_torch_se3_exp_at_and_near_zero(dtype, value_tol, grad_tol):
    gen = generator(3)
    axes = torch.randn(len(ANGLES), 3, generator=gen, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    translations = 0.1 * torch.randn(len(ANGLES), 3, generator=gen, dtype=torch.float64)
    deltas = torch.cat([axes * torch.tensor(ANGLES, dtype=torch.float64)[:, None], translations], dim=-1)
    viewmats = random_viewmats(len(ANGLES), gen)
    cotangent = torch.randn(len(ANGLES), 4, 4, generator=gen, dtype=torch.float64)
    deltas, viewmats, cotangent = deltas.to(dtype), viewmats.to(dtype), cotangent.to(dtype)

    warp_deltas = deltas.clone().requires_grad_()
    torch_deltas = deltas.clone().requires_grad_()
    ours = apply_pose_deltas(viewmats, warp_deltas)
    theirs = se3_exp(torch_deltas) @ viewmats
    torch.testing.assert_close(ours, theirs, rtol=0, atol=value_tol)
    (ours * cotangent).sum().backward()
    (theirs * cotangent).sum().backward()
    torch.testing.assert_close(warp_deltas.grad, torch_deltas.grad, rtol=0, atol=grad_tol)
    assert math.isfinite(warp_deltas.grad.abs().max().item())
