"""Every Warp kernel module builds for a CUDA architecture through NVRTC, with no GPU present.

The kernels are generic over float32/float64; their overloads are instantiated by rendering once on the CPU in
both precisions (with SH and pose deltas, the photometric loss on the render, the object-centric pose corrections, a
nearest-point search, a k-nearest mean distance and the coherence search, so every kernel runs), then each module is
compiled ahead of time for sm_80 (Warp leaves out of it, with a warning, a generic kernel no launch instantiated).
Same source as the CPU path: what passes here is what a CUDA machine runs.
"""

from __future__ import annotations

import importlib
import re

import pytest
import torch
import warp as wp
from conftest import random_scene

import warpbags
from warpbags.kernels.rasterize import LANES
from warpbags.losses import photometric_loss
from warpbags.wrapper import apply_object_deltas, least_outside_samples, mean_neighbour_distances, nearest_points

KERNEL_MODULES = ["pose", "project", "sh", "bin", "rasterize", "loss", "nearest", "knn", "coherence"]
# Kernels checked by name to be in their module's CUDA code, with how many overloads: one per precision (the render
# instantiates them, or, for the GPU-only binning the CPU never launches, their module declares both), and for the
# rasterizer one per precision and pixel block (rasterize.LANES; the CPU launches only its blocks of several pixels,
# CUDA only lanes = 1), and per depth term for its backward.
NAMED_KERNELS = {"pose": {"apply_pose_deltas_kernel": 2, "apply_object_deltas_kernel": 2},
                 "project": {"project_gaussians_kernel": 2, "project_gaussians_backward_kernel": 2},
                 "sh": {"sh_to_colors_kernel": 2, "sh_to_colors_backward_kernel": 2},
                 "bin": {"count_tiles_kernel": 2, "emit_intersections_kernel": 2},
                 "rasterize": {"rasterize_forward_kernel": 2 * len(LANES),
                               "rasterize_backward_kernel": 2 * 2 * len(LANES)}}


@pytest.mark.parametrize("module_name", KERNEL_MODULES)
def test_kernel_module_compiles_for_sm80(module_name, tmp_path):
    for dtype in (torch.float32, torch.float64):
        scene = random_scene(n=6, cams=2, width=8, height=8, dtype=dtype, sh_degree=1)
        means = scene["means"].requires_grad_()
        out, _, _ = warpbags.rasterization(**scene, sh_degree=1, pose_deltas=torch.zeros(2, 6, dtype=dtype))
        loss, _ = photometric_loss(out, torch.rand_like(out))
        loss.backward()
        assert means.grad is not None
        apply_object_deltas(torch.eye(4, dtype=dtype).repeat(2, 1, 1), torch.zeros(2, 6, dtype=dtype),
                            torch.zeros(2, 3, dtype=dtype))  # the default camera parameterization's
        nearest_points(torch.rand(5, 2, dtype=dtype), torch.rand(9, 2, dtype=dtype))  # the silhouette chamfer's
        mean_neighbour_distances(torch.rand(9, 3, dtype=dtype), 3)  # the floater removal's
        least_outside_samples(torch.rand(4, 3, dtype=dtype), torch.tensor([0, 0, 1, 1]), torch.rand(2, 3, dtype=dtype),
                              torch.rand(2, 5, dtype=dtype), torch.eye(4, dtype=dtype).repeat(2, 1, 1),
                              torch.eye(3, dtype=dtype).repeat(2, 1, 1), torch.rand(2, 8, 8), 0.0, 8.0)  # coherence

    module = importlib.import_module(f"warpbags.kernels.{module_name}")
    try:
        artifacts = wp.compile_aot_module(module, arch=80, module_dir=tmp_path)
    except Exception as error:  # only a missing NVRTC is a reason to skip; anything else fails the test
        if "nvrtc" in str(error).lower():
            pytest.skip(f"NVRTC is not available in this Warp build: {error}")
        raise
    assert artifacts, f"no CUDA artifact for {module_name}"
    for path in artifacts:
        assert path.exists() and path.stat().st_size > 1000, path
    sources = list(tmp_path.rglob("*.cu"))
    assert sources and any("float64" in p.read_text() or "double" in p.read_text() for p in sources)
    code = "".join(p.read_text() for p in sources)
    for key, count in NAMED_KERNELS.get(module_name, {}).items():
        # a kernel built inside a function (the rasterizer's, one per pixel block) is named after it too
        overloads = set(re.findall(rf"void ((?:\w+__locals__)?{key}_[0-9a-f]+)_cuda_kernel_forward\(", code))
        assert len(overloads) == count, f"{key}: CUDA code of {len(overloads)} overloads, not {count}"
