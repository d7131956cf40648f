"""warpbags.cameras: camera centres, poses from centres and pinhole projection (CPU, float64)."""

from __future__ import annotations

import torch
from random_poses import F64, generator, random_rotations, random_viewmats, skew_reference

from warpbags.cameras import (camera_centers, improper_viewmats, mean_viewmats, moved_keeping_target, pixel_directions,
                              project_points, viewmats_from_centers)


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


def test_improper_viewmats_names_sheared_scaled_and_projective_matrices():
    """Each of `improper_viewmats`' checks refuses a matrix the determinant alone passes or that `POSE_TOLERANCE`
    must catch: a shear with det 1 (orthogonality), a homogeneous scale in the last row, and a 5% scale (det 1.16);
    poses rounded to float32, as files store them, pass."""
    good = random_viewmats(7, generator(41))
    bad = good.clone()
    bad[1, :3, :3] = bad[1, :3, :3] @ torch.tensor([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    bad[3, 3, 3] = 2.0
    bad[5, :3, :3] *= 1.05
    assert improper_viewmats(good).tolist() == []
    assert improper_viewmats(good.float()).tolist() == []
    assert improper_viewmats(bad).tolist() == [1, 3, 5]


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


def test_pixel_directions_project_back_to_their_pixels():
    """Directions at unit depth through pixels of two cameras, scaled to any depth and projected, land on the
    pixels they came from."""
    Ks = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 120.0, 40.0], [0.0, 0.0, 1.0]],
                       [[80.0, 0.0, 30.5], [0.0, 80.0, 20.5], [0.0, 0.0, 1.0]]], dtype=F64)
    pixels = torch.rand(2, 5, 2, generator=generator(), dtype=F64) * 100
    directions = pixel_directions(pixels, Ks[:, None])
    assert torch.equal(directions[..., 2], torch.ones(2, 5, dtype=F64))
    for camera in range(2):
        projected, depths = project_points(torch.eye(4, dtype=F64)[None], Ks[camera:camera + 1],
                                           directions[camera] * 3.0)
        torch.testing.assert_close(projected[0], pixels[camera])
        torch.testing.assert_close(depths[0], torch.full((5,), 3.0, dtype=F64))


def test_moved_keeping_target_keeps_the_target_on_its_ray_and_turns_least():
    gen = generator(3)
    viewmats = random_viewmats(6, gen).double()
    target = torch.randn(3, generator=gen, dtype=torch.float64) * 0.1
    in_front = (viewmats[:, :3, :3] @ target + viewmats[:, :3, 3])[:, 2] > 0.5
    viewmats = viewmats[in_front]
    assert len(viewmats) >= 2
    Ks = torch.tensor([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]], dtype=torch.float64).expand(len(viewmats), 3, 3)
    centers = camera_centers(viewmats) + 0.3 * torch.randn(len(viewmats), 3, generator=gen, dtype=torch.float64)
    moved = moved_keeping_target(viewmats, centers, target)
    torch.testing.assert_close(camera_centers(moved), centers)
    before, _ = project_points(viewmats, Ks, target[None])
    after, _ = project_points(moved, Ks, target[None])
    torch.testing.assert_close(after, before)  # the target stays where the camera saw it
    # The turn is the smallest one: its axis is perpendicular to the ray, so the roll about that ray is unchanged.
    turn = moved[:, :3, :3] @ viewmats[:, :3, :3].transpose(1, 2)
    ray = viewmats[:, :3, :3] @ target + viewmats[:, :3, 3]
    axis = torch.stack([turn[:, 2, 1] - turn[:, 1, 2], turn[:, 0, 2] - turn[:, 2, 0], turn[:, 1, 0] - turn[:, 0, 1]], -1)
    assert ((axis * ray).sum(-1).abs() <= 1e-9 * ray.norm(dim=-1)).all()
    # Not moving is the identity.
    torch.testing.assert_close(moved_keeping_target(viewmats, camera_centers(viewmats), target), viewmats)


def test_mean_viewmats_of_turns_either_way_is_the_middle_pose():
    """A camera turned by +a and -a about one axis averages to the unturned pose, its centres to their mean; the
    mean of one estimate is that estimate, and of nearly opposite rotations still a rotation."""
    viewmats = random_viewmats(3, generator(4))
    axis = torch.tensor([0.2, -0.5, 0.8], dtype=F64)
    turns = [torch.linalg.matrix_exp(skew_reference(axis * sign * 0.3)) for sign in (1, -1)]
    rotations = [turn @ viewmats[:, :3, :3] for turn in turns]
    centers = [camera_centers(viewmats) + shift for shift in (0.1, -0.3)]
    mean = mean_viewmats(sum(rotations), sum(centers), 2)
    torch.testing.assert_close(mean[:, :3, :3], viewmats[:, :3, :3], rtol=0, atol=1e-12)
    torch.testing.assert_close(camera_centers(mean), camera_centers(viewmats) - 0.1, rtol=0, atol=1e-12)
    torch.testing.assert_close(mean_viewmats(viewmats[:, :3, :3], camera_centers(viewmats), 1), viewmats,
                               rtol=0, atol=1e-12)
    flipped = random_rotations(1, generator(5))[0]
    opposite = mean_viewmats((flipped + torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)) @ flipped)[None],
                             torch.zeros(1, 3, dtype=F64), 2)[0, :3, :3]
    torch.testing.assert_close(opposite @ opposite.T, torch.eye(3, dtype=F64), rtol=0, atol=1e-12)
    assert torch.linalg.det(opposite) > 0
