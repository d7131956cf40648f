"""warpbags.camera_paths: turntables, azimuth order and cameras between neighbours (CPU, float64)."""

from __future__ import annotations

import torch
from random_poses import F64

from warpbags.camera_paths import azimuth_order, interpolated_viewmats, turntable_viewmats
from warpbags.cameras import camera_centers
from warpbags.lie import rotation_error_deg

def test_interpolated_viewmats_walk_the_orbit_between_neighbouring_cameras():
    base = torch.eye(4, dtype=F64)
    base[2, 3] = 4.0
    orbit = turntable_viewmats(base[None], 16)
    shuffled = orbit[::2][torch.tensor([3, 0, 6, 1, 5, 2, 7, 4])]  # 8 cameras 45 degrees apart, out of order
    order = azimuth_order(shuffled)
    assert len(set(order.tolist())) == 8
    # Neighbours in azimuth order are 45 degrees apart (2 turntable steps of 16).
    angles = rotation_error_deg(shuffled[order, :3, :3], shuffled[order.roll(-1), :3, :3])
    torch.testing.assert_close(angles, torch.full((8,), 45.0, dtype=F64))
    ends = interpolated_viewmats(shuffled, torch.tensor([0, 5]), torch.tensor([0.0, 1.0], dtype=F64))
    torch.testing.assert_close(ends, shuffled[order[[0, 6]]], rtol=0, atol=1e-12)
    middles = interpolated_viewmats(shuffled, torch.arange(8), torch.full((8,), 0.5, dtype=F64))
    # Each midpoint is an odd turntable frame (the frames between the even ones), each found exactly once.
    distances = torch.cdist(middles[:, :3, :].flatten(1), orbit[1::2, :3, :].flatten(1))
    assert distances.min(dim=1).values.max().item() < 1e-9
    assert sorted(distances.argmin(dim=1).tolist()) == list(range(8))
    quarter = interpolated_viewmats(shuffled, torch.arange(8), torch.full((8,), 0.25, dtype=F64))
    torch.testing.assert_close(camera_centers(quarter).norm(dim=-1), torch.full((8,), 4.0, dtype=F64))
