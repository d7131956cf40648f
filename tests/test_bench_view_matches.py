"""bench/view_matches.py: SIFT matches between two views of a textured sphere are found, kept and counted true at
the poses that rendered them, and no longer true when one camera is turned (a bad scene or option is one error
line: tests/test_bench_errors.py)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import torch
from conftest import textured_sphere_pair

from warpbags.lie import so3_exp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from view_matches import view_matches  # noqa: E402


def _scene():
    images, masks, viewmats, Ks = textured_sphere_pair()
    return SimpleNamespace(name="sphere", train_views=lambda views: [0, 1], images=images.float(), masks=masks,
                           viewmats=viewmats.float(), Ks=Ks.float(), width=images.shape[2], height=images.shape[1])


def test_matches_are_true_at_the_rendering_poses_and_not_once_a_camera_turns():
    scene = _scene()
    result = view_matches(scene, 2, features=2000, ratio=0.8, true_px=2.0, ransac_px=1.5, min_inliers=15)
    (pair,) = result["pairs"]
    axes = scene.viewmats[:, 2, :3].double()
    assert pair["views"] == [0, 1] and abs(pair["angle_deg"] - math.degrees(math.acos(axes[0] @ axes[1]))) < 1e-3
    assert pair["matches"] >= 50 and pair["true"] >= 0.9 * pair["matches"]
    assert pair["kept"] and pair["right"] and pair["true_inliers"] >= 0.9 * pair["inliers"]
    assert (result["with_true"], result["kept"], result["right"]) == (1, 1, 1)

    turned = scene.viewmats.clone()  # camera 1 turned by 3 deg about its own centre, across the epipolar lines
    turned[1, :3] = so3_exp(torch.tensor([math.radians(3.0), 0.0, 0.0])) @ turned[1, :3]
    scene.viewmats = turned
    result = view_matches(scene, 2, features=2000, ratio=0.8, true_px=2.0, ransac_px=1.5, min_inliers=15)
    (pair_turned,) = result["pairs"]
    assert pair_turned["matches"] == pair["matches"] and pair_turned["kept"]  # the images did not change
    assert pair_turned["true"] < 0.1 * pair["matches"] and not pair_turned["right"]
    assert (result["with_true"], result["right"]) == (0, 0)
