"""bench/hull_depths.py: the depth maps of a carved visual hull lie on the object, and a bad scene is one error line
(tests/test_bench_errors.py)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch
from conftest import look_at

from warpbags.cameras import pixel_directions
from warpbags.init import visual_hull

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from hull_depths import hull_depth_maps, occupancy_grid  # noqa: E402


def _sphere_views(radius: float, size: int = 48):
    """Masks and exact z-depth maps of a sphere of `radius` at the origin, seen by 8 cameras around it at distance 4
    (elevations -30 to 60 deg)."""
    eyes = []
    for index in range(8):
        azimuth, elevation = 2 * math.pi * index / 8, math.radians(-30 + 90 * (index % 4) / 3)
        eyes.append(4.0 * torch.tensor([math.cos(elevation) * math.cos(azimuth),
                                        math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]))
    viewmats = torch.stack([look_at(eye.double(), torch.zeros(3, dtype=torch.float64)) for eye in eyes])
    K = torch.tensor([[60.0, 0.0, size / 2], [0.0, 60.0, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    Ks = K.expand(8, 3, 3)
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    pixels = torch.stack([cols + 0.5, rows + 0.5], -1).double()
    directions = pixel_directions(pixels, K)  # camera frame, z = 1
    depths = torch.zeros(8, size, size, dtype=torch.float64)
    # |t d - c|^2 = r^2 for the depth t along the optical axis (d has z = 1, c the sphere's centre in camera axes)
    a = (directions * directions).sum(-1)
    for view, viewmat in enumerate(viewmats):
        centre = viewmat[:3, 3]
        b = (directions * centre).sum(-1)
        disc = b * b - a * (centre @ centre - radius**2)
        depths[view] = torch.where(disc > 0, (b - disc.clamp_min(0).sqrt()) / a, torch.zeros(()))
    return (depths > 0).float(), depths, viewmats, Ks


def test_hull_depth_maps_lie_on_the_object():
    """With 8 views of a sphere the hull's first hit along each mask pixel's ray is on the sphere but for the
    masks' own pixels (one pixel is 0.067 units at the sphere's distance: a mask erodes or grows the silhouette by
    up to half of one, which a ray at a slant turns into more depth); off the masks there is no value."""
    masks, exact, viewmats, Ks = _sphere_views(radius=0.8)
    points, voxel = visual_hull(masks, viewmats, Ks, resolution=64, missed_views=0)
    depths = hull_depth_maps(points, voxel, masks, viewmats, Ks).double()
    assert depths.shape == masks.shape and (depths[masks == 0] == 0).all()
    inside = (masks > 0) & (depths > 0)
    assert inside.sum() > 0.98 * masks.sum()
    pixel = 4.0 / 60.0
    gap = (exact - depths)[inside].abs()
    assert gap.median() < 0.5 * pixel and torch.quantile(gap, 0.98) < 2 * pixel


def test_each_hull_voxel_is_the_grid_cell_around_its_centre():
    masks, _, viewmats, Ks = _sphere_views(radius=0.8)
    points, voxel = visual_hull(masks, viewmats, Ks, resolution=40, missed_views=0)
    grid, lower = occupancy_grid(points.double(), voxel)
    assert int(grid.sum()) == len(points)
    cells = torch.nonzero(grid).double()
    torch.testing.assert_close(torch.sort(lower + (cells + 0.5) * voxel, dim=0).values,
                               torch.sort(points.double(), dim=0).values, rtol=0, atol=1e-5)
