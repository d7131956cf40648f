"""warpbags.correspondences: matches between two rendered views of a textured sphere, the fundamental matrix and
Sampson distance of the poses, and the epipolar loss that turns a camera back to where the matches say it is."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import textured_sphere_pair

from warpbags.cameras import project_points
from warpbags.correspondences import (ViewMatches, epipolar_loss, find_view_matches, fundamental_matrices,
                                      sampson_distances)
from warpbags.lie import rotation_error_deg, so3_exp

SIZE = 160


def turned(viewmats: torch.Tensor, view: int, degrees: float, axis: int = 1) -> torch.Tensor:
    """`viewmats` with camera `view` turned about its own centre and camera axis `axis` by `degrees`."""
    omega = torch.zeros(3, dtype=viewmats.dtype)
    omega[axis] = math.radians(degrees)
    out = viewmats.clone()
    out[view, :3] = so3_exp(omega) @ out[view, :3]
    return out


def test_sampson_distance_is_zero_for_projections_and_about_the_offset_across_the_epipolar_line():
    _, _, viewmats, Ks = textured_sphere_pair(SIZE)
    points = torch.rand(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) - 0.5
    pixels, _ = project_points(viewmats, Ks, points)  # [2,50,2]
    F = fundamental_matrices(viewmats[0], viewmats[1], Ks[0], Ks[1])
    assert sampson_distances(F, pixels[0], pixels[1]).max() < 1e-8
    line = (F @ torch.cat([pixels[0], torch.ones(50, 1, dtype=torch.float64)], 1).T).T
    normal = line[:, :2] / line[:, :2].norm(dim=1, keepdim=True)
    # b moved 3 px across its epipolar line: a, half as far from its own line, shares the distance
    moved = pixels[1] + 3.0 * normal
    shifted = sampson_distances(F, pixels[0], moved)
    assert 1.0 < shifted.min() and shifted.max() < 3.0 + 1e-6
    # Sampson's first-order distance, written out: |x_b' F x_a| over the gradient's norm, both lines' normals (b's
    # line alone, the one-sided epipolar distance, reads exactly 3 and passed the bounds above)
    homogeneous_a = torch.cat([pixels[0], torch.ones(50, 1, dtype=torch.float64)], 1)
    homogeneous_b = torch.cat([moved, torch.ones(50, 1, dtype=torch.float64)], 1)
    line_b, line_a = homogeneous_a @ F.T, homogeneous_b @ F
    expected = (homogeneous_b * line_b).sum(1).abs() / (line_b[:, :2].square().sum(1) + line_a[:, :2].square().sum(1)).sqrt()
    torch.testing.assert_close(shifted, expected, rtol=1e-9, atol=0)
    assert shifted.max() < 2.9


def test_find_view_matches_keeps_the_pairs_with_enough_inliers_and_their_matches_are_right():
    images, masks, viewmats, Ks = textured_sphere_pair(SIZE)
    matches = find_view_matches(images, masks, min_inliers=15)
    assert matches.pairs == [(0, 1)] and len(matches) >= 50 and matches.size == (SIZE, SIZE)
    F = fundamental_matrices(viewmats[0], viewmats[1], Ks[0], Ks[1])
    distances = sampson_distances(F, matches.pixels_a, matches.pixels_b)
    assert (distances < 1.0).float().mean() > 0.95  # SIFT locates blobs to a fraction of a pixel
    assert len(find_view_matches(images, masks, min_inliers=len(matches) + 1)) == 0
    assert len(find_view_matches(images, masks, min_inliers=len(matches))) == len(matches)  # "at least" min_inliers
    masked = find_view_matches(images, torch.zeros(2, SIZE, SIZE), min_inliers=8)  # nothing inside the masks
    assert len(masked) == 0 and masked.pixels_a.shape == (0, 2)


def test_view_matches_scale_with_the_image_and_renumber_with_a_subset():
    matches = ViewMatches(torch.tensor([0, 1, 0]), torch.tensor([2, 2, 1]),
                          torch.tensor([[10.0, 20.0], [4.0, 6.0], [1.0, 1.0]], dtype=torch.float64),
                          torch.tensor([[30.0, 40.0], [8.0, 2.0], [2.0, 2.0]], dtype=torch.float64), size=(100, 80))
    half = matches.scaled_to(50, 20)
    assert half.size == (50, 20) and half.pixels_a[0].tolist() == [5.0, 5.0] and half.pixels_b[1].tolist() == [4.0, 0.5]
    kept = matches.subset([0, 2])  # view 1 dropped: its matches go, view 2 becomes 1
    assert kept.views_a.tolist() == [0] and kept.views_b.tolist() == [1] and kept.pixels_b.tolist() == [[30.0, 40.0]]


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_epipolar_loss_turns_a_camera_back_to_the_matches(axis):
    """What the term is for: the matches alone (no image, no Gaussian) fix one camera's orientation relative to the
    other's. One turned by 3 deg about any axis is solved back to within 0.4 deg by minimizing the loss over its
    rotation, to the same pose from every start. (The turns that move points across the epipolar lines are fixed
    sharply; the one that moves them along the lines, about the image axis across the baseline, only through the
    lines' convergence: the loss's curvature there is 1e-4 of the others', and the solve ends 0.32 deg off along it
    in a 34 deg field of view.)"""
    images, masks, viewmats, Ks = textured_sphere_pair(SIZE)
    matches = find_view_matches(images, masks, min_inliers=15)
    start = turned(viewmats, 1, 3.0, axis)
    loss_at = lambda poses: float(epipolar_loss(poses, Ks, matches))  # noqa: E731
    assert loss_at(viewmats) < 0.5 and loss_at(start) > 5 * loss_at(viewmats)
    omega = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.LBFGS([omega], max_iter=100, line_search_fn="strong_wolfe")

    def corrected() -> torch.Tensor:
        rows = so3_exp(omega) @ start[1, :3]
        return torch.stack([start[0], torch.cat([rows, start[1, 3:]], 0)])

    def closure():
        optimizer.zero_grad()
        loss = epipolar_loss(corrected(), Ks, matches)
        loss.backward()
        return loss

    optimizer.step(closure)
    with torch.no_grad():
        error = float(rotation_error_deg(corrected()[1, :3, :3], viewmats[1, :3, :3]))
    assert error < 0.4


def test_epipolar_loss_without_matches_is_zero_and_keeps_the_graph():
    _, _, viewmats, Ks = textured_sphere_pair(SIZE)
    empty = ViewMatches(torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                        torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, 2, dtype=torch.float64), (SIZE, SIZE))
    poses = viewmats.clone().requires_grad_(True)
    loss = epipolar_loss(poses, Ks, empty)
    loss.backward()
    assert loss.item() == 0.0 and poses.grad is not None and not poses.grad.any()
