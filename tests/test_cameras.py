"""warpbags.cameras: camera centres, poses from centres and pinhole projection (CPU, float64)."""

from __future__ import annotations

import torch
from random_poses import F64, generator, random_rotations, random_viewmats

from warpbags.cameras import camera_centers, project_points, viewmats_from_centers


def test_camera_centers_map_to_camera_origin():
    viewmats = random_viewmats(5, generator(12))
    centers = camera_centers(viewmats)
    homogeneous = torch.cat([centers, torch.ones(5, 1, dtype=F64)], dim=-1)
    in_camera = (viewmats @ homogeneous[..., None])[..., 0]
    torch.testing.assert_close(in_camera[:, :3], torch.zeros(5, 3, dtype=F64), rtol=0, atol=1e-13)
    # A camera at (1, 2, 3) looking down +z with identity rotation has t = -c.
    simple = torch.eye(4, dtype=F64)
    simple[:3, 3] = torch.tensor([-1.0, -2.0, -3.0], dtype=F64)
    torch.testing.assert_close(camera_centers(simple[None])[0], torch.tensor([1.0, 2.0, 3.0], dtype=F64))


def test_viewmats_from_centers_inverts_camera_centers():
    gen = generator(13)
    rotations = random_rotations(6, gen)
    centers = torch.randn(6, 3, generator=gen, dtype=F64)
    viewmats = viewmats_from_centers(rotations, centers)
    torch.testing.assert_close(camera_centers(viewmats), centers, rtol=0, atol=1e-14)
    assert torch.equal(viewmats[:, :3, :3], rotations)
    assert torch.equal(viewmats[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64).expand(6, 4))


def test_project_points_is_the_pinhole_model():
    viewmats = torch.eye(4, dtype=F64)[None]
    Ks = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 120.0, 40.0], [0.0, 0.0, 1.0]]], dtype=F64)
    points = torch.tensor([[0.1, -0.2, 2.0], [0.0, 0.0, -1.0]], dtype=F64)
    pixels, depths = project_points(viewmats, Ks, points)
    torch.testing.assert_close(pixels[0, 0], torch.tensor([55.0, 28.0], dtype=F64))
    torch.testing.assert_close(depths[0], torch.tensor([2.0, -1.0], dtype=F64))
    assert torch.isfinite(pixels).all()  # the point behind the camera stays finite; its depth marks it
