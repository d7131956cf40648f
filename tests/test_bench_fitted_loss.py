"""bench/fitted_loss.py: the images' consistency across views is high where the cameras are right and falls when
one of them is turned (a bad scene is one error line: tests/test_bench_errors.py)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch
from conftest import look_at

from warpbags.cameras import pixel_directions

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from fitted_loss import cross_view_consistency  # noqa: E402


def _textured_sphere_views(size: int = 64):
    """8 cameras at distance 4 around a sphere of radius 0.8 whose colour is a smooth function of the surface point
    (a wavelength of about 14 pixels): images, masks, exact z-depths, viewmats, Ks (float64)."""
    eyes = []
    for index in range(8):
        azimuth, elevation = 2 * math.pi * index / 8, math.radians(-20 + 40 * (index % 2))
        eyes.append(4.0 * torch.tensor([math.cos(elevation) * math.cos(azimuth),
                                        math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]))
    viewmats = torch.stack([look_at(eye.double(), torch.zeros(3, dtype=torch.float64)) for eye in eyes])
    K = torch.tensor([[100.0, 0.0, size / 2], [0.0, 100.0, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    Ks = K.expand(8, 3, 3).contiguous()
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    directions = pixel_directions(torch.stack([cols + 0.5, rows + 0.5], -1).double(), K)
    a = (directions * directions).sum(-1)
    images, depths = torch.zeros(8, size, size, 3, dtype=torch.float64), torch.zeros(8, size, size, dtype=torch.float64)
    frequencies = torch.tensor([[11.0, 3.0, 5.0], [4.0, 12.0, -3.0], [-6.0, 5.0, 10.0]], dtype=torch.float64)
    for view, viewmat in enumerate(viewmats):
        centre = viewmat[:3, 3]  # the sphere's centre in camera axes
        b = (directions * centre).sum(-1)
        disc = b * b - a * (centre @ centre - 0.8**2)
        depth = torch.where(disc > 0, (b - disc.clamp_min(0).sqrt()) / a, torch.zeros(()))
        world = (directions * depth[..., None] - centre) @ viewmat[:3, :3]
        images[view] = torch.where((depth > 0)[..., None], 0.5 + 0.4 * torch.sin(world @ frequencies.T), torch.ones(()))
        depths[view] = depth
    return images, (depths > 0).double(), depths, viewmats, Ks


def _turned(viewmat: torch.Tensor, degrees: float) -> torch.Tensor:
    """`viewmat` with the camera turned about its own y axis."""
    angle = math.radians(degrees)
    turn = torch.eye(4, dtype=viewmat.dtype)
    turn[0, 0], turn[0, 2], turn[2, 0], turn[2, 2] = math.cos(angle), math.sin(angle), -math.sin(angle), math.cos(angle)
    return turn @ viewmat


def test_consistency_is_high_at_the_true_poses_and_falls_when_a_camera_turns():
    images, masks, depths, viewmats, Ks = _textured_sphere_views()
    pairs = cross_view_consistency(images, masks, depths, viewmats, Ks)
    assert len(pairs) == 8 * 7
    neighbours = [p for p in pairs if (p["j"] - p["i"]) % 8 in (1, 7)]  # 45 deg apart: they share the most surface
    assert all(p["pixels"] > 100 for p in neighbours)
    assert max(p["l1"] for p in neighbours) < 0.03 and min(p["ncc"] for p in neighbours) > 0.95
    # camera 0 turned by 2 deg (3.5 px at this focal) with its image and depth as they were: its pairs disagree
    moved = viewmats.clone()
    moved[0] = _turned(viewmats[0], 2.0)
    turned_pairs = [p for p in cross_view_consistency(images, masks, depths, moved, Ks)
                    if 0 in (p["i"], p["j"]) and (p["j"] - p["i"]) % 8 in (1, 7)]
    assert all(p["pixels"] > 100 for p in turned_pairs)
    assert min(p["l1"] for p in turned_pairs) > 3 * max(p["l1"] for p in neighbours)
    assert max(p["ncc"] for p in turned_pairs) < 0.8


def test_pixels_hidden_from_the_other_view_do_not_count():
    """Views 180 deg apart see opposite halves of the sphere: nothing lands in front of the other view's surface."""
    images, masks, depths, viewmats, Ks = _textured_sphere_views()
    opposite = [p for p in cross_view_consistency(images, masks, depths, viewmats, Ks) if (p["j"] - p["i"]) % 8 == 4]
    assert all(p["pixels"] < 20 and math.isnan(p["l1"]) and math.isnan(p["ncc"]) for p in opposite)
