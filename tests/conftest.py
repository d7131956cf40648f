"""Shared fixtures: tiny random scenes and the device list (cpu here, cuda where present)."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from typing import Callable

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


def textured_sphere_pair(size: int = 160) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two views of a unit sphere covered in random blobs (what SIFT finds), for feature matching: images
    [2,H,W,3] in [0, 1], masks [2,H,W], world-to-camera [2,4,4] and intrinsics [2,3,3] (float64). The cameras are
    35 deg apart at different distances and heights, so nothing is symmetric between the views, and the surface is
    curved, so the matches fix the cameras' relative orientation about every axis (a plane would not)."""
    import cv2
    import numpy as np

    from warpbags.cameras import pixel_directions

    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.random((512, 1024)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())  # latitude x longitude
    eyes = [torch.tensor([distance * math.cos(math.radians(a)), distance * math.sin(math.radians(a)), height],
                         dtype=torch.float64) for a, distance, height in ((-10, 4.0, 0.4), (25, 3.2, -0.3))]
    viewmats = torch.stack([look_at(eye, torch.tensor([0.05, 0.0, 0.1], dtype=torch.float64)) for eye in eyes])
    K = torch.tensor([[260.0, 0.0, size / 2], [0.0, 260.0, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    directions = pixel_directions(torch.stack([cols + 0.5, rows + 0.5], -1).double(), K)  # [H,W,3] camera axes
    images, masks = [], []
    for viewmat in viewmats:
        rotation, centre = viewmat[:3, :3], -viewmat[:3, :3].T @ viewmat[:3, 3]
        rays = directions @ rotation  # world directions (R^T d)
        b = (rays * centre).sum(-1)
        disc = b * b - (rays * rays).sum(-1) * (centre @ centre - 1.0)
        hit = disc > 0
        depth = (-b - disc.clamp_min(0).sqrt()) / (rays * rays).sum(-1)
        points = centre + rays * depth[..., None]  # on the unit sphere where hit
        longitude = (torch.atan2(points[..., 1], points[..., 0]) / (2 * math.pi) + 0.5) * 1023  # seam behind
        latitude = torch.acos(points[..., 2].clamp(-1, 1)) / math.pi * 511
        grey = cv2.remap(texture, longitude.float().numpy(), latitude.float().numpy(), cv2.INTER_LINEAR)
        grey = np.where(hit.numpy(), grey, 1.0).astype(np.float32)
        images.append(torch.from_numpy(np.repeat(grey[..., None], 3, -1)))
        masks.append(hit.float())
    return torch.stack(images), torch.stack(masks), viewmats, K.expand(2, 3, 3).contiguous()


def stopped_by_sigterm(arguments: list[str], ready: Callable[[], bool], timeout: float = 120) -> tuple[int, str]:
    """Run `warpbags ARGUMENTS` in a process, send it SIGTERM (as `kill` does) once `ready()` holds (it is written
    into its output folder), and return its (exit code, output)."""
    process = subprocess.Popen([sys.executable, "-m", "warpbags.cli.main", *arguments], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT)
    deadline = time.monotonic() + timeout
    while not ready() and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    output = process.communicate(timeout=timeout)[0].decode()
    return process.returncode, output
