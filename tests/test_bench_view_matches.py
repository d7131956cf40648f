"""bench/view_matches.py: SIFT matches between two views of a textured plane are found, kept and counted true at
the poses that rendered them, and no longer true when one camera is turned (a bad scene or option is one error
line: tests/test_bench_errors.py)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch
from conftest import look_at

from warpbags.cameras import pixel_directions, project_points
from warpbags.lie import so3_exp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from view_matches import fundamental_matrix, sampson_distance, view_matches  # noqa: E402

SIZE = 160


def _plane_scene():
    """Two cameras 35 deg apart at different distances looking at a plane (z = 0) covered in random blobs: images,
    viewmats, Ks. Nothing is symmetric between them, so a fundamental matrix of the wrong way round fails."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.random((512, 512)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    eyes = [torch.tensor([0.3 + distance * math.sin(math.radians(a)) * 0.3, -distance * math.sin(math.radians(a)),
                          distance * math.cos(math.radians(a))]) for a, distance in ((-10, 4.0), (25, 3.2))]
    target = torch.tensor([0.1, 0.05, 0.0], dtype=torch.float64)
    viewmats = torch.stack([look_at(eye.double(), target) for eye in eyes])
    K = torch.tensor([[200.0, 0.0, SIZE / 2], [0.0, 200.0, SIZE / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    rows, cols = torch.meshgrid(torch.arange(SIZE), torch.arange(SIZE), indexing="ij")
    directions = pixel_directions(torch.stack([cols + 0.5, rows + 0.5], -1).double(), K)  # [H,W,3] camera axes
    images = []
    for viewmat in viewmats:
        rotation_t, centre = viewmat[:3, :3].T, -viewmat[:3, :3].T @ viewmat[:3, 3]
        rays = directions @ rotation_t.T  # world directions
        depth = -centre[2] / rays[..., 2]
        points = centre + rays * depth[..., None]  # on z = 0, within +-1.5
        u = ((points[..., 0] + 1.5) / 3.0 * 511).float().numpy()
        v = ((points[..., 1] + 1.5) / 3.0 * 511).float().numpy()
        grey = cv2.remap(texture, u, v, cv2.INTER_LINEAR)
        images.append(torch.from_numpy(np.repeat(grey[..., None], 3, -1)))
    return SimpleNamespace(name="plane", train_views=lambda views: [0, 1], images=torch.stack(images), masks=None,
                           viewmats=viewmats.float(), Ks=K.float().expand(2, 3, 3), width=SIZE, height=SIZE)


def test_sampson_distance_is_zero_for_projections_and_grows_off_the_epipolar_line():
    scene = _plane_scene()
    points = torch.rand(50, 3, dtype=torch.float64) - 0.5
    pixels, _ = project_points(scene.viewmats.double(), scene.Ks.double(), points)  # [2,50,2]
    F = fundamental_matrix(scene.viewmats[0].double().numpy(), scene.viewmats[1].double().numpy(),
                           scene.Ks[0].double().numpy(), scene.Ks[1].double().numpy())
    a, b = pixels[0].numpy(), pixels[1].numpy()
    assert sampson_distance(F, a, b).max() < 1e-8
    # moved by 3 px across its epipolar line, b's Sampson distance is about 3 px (a, half as far off, shares it)
    line = np.c_[a, np.ones(len(a))] @ F.T
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    shifted = sampson_distance(F, a, b + 3.0 * normal)
    assert 1.0 < shifted.min() and shifted.max() < 3.0 + 1e-6


def test_matches_are_true_at_the_rendering_poses_and_not_once_a_camera_turns():
    scene = _plane_scene()
    result = view_matches(scene, 2, features=2000, ratio=0.8, true_px=2.0, ransac_px=1.5, min_inliers=15)
    (pair,) = result["pairs"]
    axes = scene.viewmats[:, 2, :3].double()
    assert pair["views"] == [0, 1] and abs(pair["angle_deg"] - math.degrees(math.acos(axes[0] @ axes[1]))) < 1e-3
    assert pair["matches"] >= 50 and pair["true"] >= 0.9 * pair["matches"]
    assert pair["kept"] and pair["right"] and pair["true_inliers"] >= 0.9 * pair["inliers"]
    assert (result["with_true"], result["kept"], result["right"]) == (1, 1, 1)

    turned = scene.viewmats.clone()  # camera 1 turned by 3 deg about its own centre, across the epipolar lines
    turned[1, :3] = so3_exp(torch.tensor([0.0, math.radians(3.0), 0.0])).float() @ turned[1, :3]
    scene.viewmats = turned
    result = view_matches(scene, 2, features=2000, ratio=0.8, true_px=2.0, ransac_px=1.5, min_inliers=15)
    (pair_turned,) = result["pairs"]
    assert pair_turned["matches"] == pair["matches"] and pair_turned["kept"]  # the images did not change
    assert pair_turned["true"] < 0.1 * pair["matches"] and not pair_turned["right"]
    assert (result["with_true"], result["right"]) == (0, 0)
