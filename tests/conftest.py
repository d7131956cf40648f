"""Shared fixtures: tiny random scenes and the device list (cpu here, cuda where present)."""

from __future__ import annotations

import math

import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(autouse=True, scope="session")
def _torch_threads():
    # Warp's CPU launches use their own host threads; torch's idle OpenMP workers would spin against them.
    torch.set_num_threads(1)


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """World-to-camera matrix (OpenCV axes) of a camera at `eye` looking at `target`, world z up."""
    forward = target - eye
    forward = forward / forward.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype)
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-6:
        right = torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    viewmat = torch.eye(4, dtype=eye.dtype)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ eye
    return viewmat


def random_scene(n=30, cams=2, width=24, height=20, dtype=torch.float64, seed=0, sh_degree=None, spread=0.6,
                 scale_range=(0.03, 0.15), device="cpu"):
    """Gaussians in a ball around the origin seen by `cams` cameras on a circle of radius 3."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2 * spread
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    lo, hi = scale_range
    scales = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.1 + 0.85 * torch.rand(n, generator=g, dtype=dtype)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=dtype)
    else:
        colors = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=dtype)
    viewmats, Ks = [], []
    for c in range(cams):
        angle = 2 * math.pi * c / max(cams, 1) + 0.3
        eye = torch.tensor([3 * math.cos(angle), 3 * math.sin(angle), 0.8 + 0.2 * c], dtype=dtype)
        viewmats.append(look_at(eye, torch.zeros(3, dtype=dtype)))
        focal = 1.1 * max(width, height)
        Ks.append(torch.tensor([[focal, 0, width / 2 + 0.3], [0, focal * 1.02, height / 2 - 0.2], [0, 0, 1]], dtype=dtype))
    scene = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                 viewmats=torch.stack(viewmats), Ks=torch.stack(Ks), width=width, height=height)
    return {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
