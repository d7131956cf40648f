"""Pose noise for a scene: perturbed copies of its (normalized) world-to-camera poses; the true ones stay put."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpbags.data.scene import Scene
from warpbags.pose import perturb_viewmats


@dataclass(frozen=True)
class PoseNoise:
    """Per-camera pose noise in normalized scene units (camera orbit radius `ORBIT_RADIUS`).

    Attributes:
        rot_std_deg: rotation angle ~ N(0, rot_std_deg^2) degrees about a uniformly random axis (--rot-noise-deg).
        trans_std: camera-centre offset ~ N(0, trans_std^2 I) (--trans-noise).
        seed: seeds the draw.
        rot_fixed_deg: instead of rot_std_deg, rotate every camera by exactly this angle (random axis).
    """

    rot_std_deg: float = 0.0
    trans_std: float = 0.0
    seed: int = 0
    rot_fixed_deg: float | None = None


def noisy_viewmats(scene: Scene, noise: PoseNoise) -> torch.Tensor:
    """[C,4,4] perturbed world-to-camera poses in the scene's normalized world (`scene.viewmats` stays the truth).

    Both are in the same normalized frame, so `scene.normalization.invert_viewmats` exports either.
    """
    return perturb_viewmats(scene.viewmats, noise.rot_std_deg, noise.trans_std, noise.seed, noise.rot_fixed_deg)
