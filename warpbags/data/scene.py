"""The `Scene` every loader returns, and the reversible scene normalization.

Conventions (the renderer relies on them):
- `viewmats [C,4,4]` float32 world-to-camera, OpenCV camera axes (x right, y down, z forward).
- `Ks [C,3,3]` float32 pinhole intrinsics at the loaded image resolution, pixel centres at (x+0.5, y+0.5).
- `images [C,H,W,3]` float32 RGB in [0,1]; `masks [C,H,W]` float32 in {0,1}; `depths [C,H,W]` float32, 0 = no value.
- Split indices are 0-based into the images sorted by name.
"""

from __future__ import annotations

from collections.abc import Container
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from warpbags.cameras import camera_centers
from warpbags.configs.train import ORBIT_RADIUS  # noqa: F401 - the normalization's radius, imported from here too
from warpbags.correspondences import ViewMatches
from warpbags.errors import WarpbagsError

DEFAULT_SPLIT_SIZES = (4, 6, 9)
"""Training-view counts every scene has a split for (`sparse_{size}.txt`, else farthest-point views): the
sparse-view protocol of GaussianObject."""


@dataclass(frozen=True)
class SceneNormalization:
    """The similarity `x_normalized = scale * (x_source - center)` from source (e.g. COLMAP) to normalized world.

    Camera rotations are unchanged; camera-space lengths (depths) scale by `scale`.

    Attributes:
        center: [3] float64, the object centre in source world coordinates.
        scale: source-to-normalized length factor.
    """

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0

    @staticmethod
    def identity() -> SceneNormalization:
        return SceneNormalization()

    def to_dict(self) -> dict:
        """As a run's config.json stores it (`from_dict` reads it back)."""
        return {"center": list(self.center), "scale": self.scale}

    @staticmethod
    def from_dict(values: dict) -> SceneNormalization:
        """What `to_dict` wrote.

        Raises:
            WarpbagsError: `values` is not {"center": [x, y, z], "scale": s} with finite numbers and s > 0 (the
                caller names the file it came from).
        """
        try:
            center, scale = tuple(float(v) for v in values["center"]), float(values["scale"])
        except (KeyError, TypeError, ValueError):
            center, scale = (), float("nan")
        if len(center) != 3 or not np.isfinite(center).all() or not np.isfinite(scale) or scale <= 0:
            raise WarpbagsError(f'normalization must be {{"center": [x, y, z], "scale": s > 0}}, got {values!r}')
        return SceneNormalization(center, scale)

    def matrix(self) -> np.ndarray:
        """[4,4] float64 homogeneous source-to-normalized transform."""
        transform = np.eye(4)
        transform[:3, :3] *= self.scale
        transform[:3, 3] = -self.scale * np.asarray(self.center)
        return transform

    def apply_points(self, points: torch.Tensor) -> torch.Tensor:
        """Source-world points [..., 3] -> normalized-world points [..., 3]."""
        center = torch.as_tensor(self.center, dtype=points.dtype, device=points.device)
        return (points - center) * self.scale

    def invert_points(self, points: torch.Tensor) -> torch.Tensor:
        """Normalized-world points [..., 3] -> source-world points [..., 3]."""
        center = torch.as_tensor(self.center, dtype=points.dtype, device=points.device)
        return points / self.scale + center

    def apply_viewmats(self, viewmats: torch.Tensor) -> torch.Tensor:
        """Source world-to-camera [C,4,4] -> normalized world-to-camera [C,4,4] (camera units scaled too)."""
        center = torch.as_tensor(self.center, dtype=viewmats.dtype, device=viewmats.device)
        out = viewmats.clone()
        out[..., :3, 3] = self.scale * (viewmats[..., :3, 3] + viewmats[..., :3, :3] @ center)
        return out

    def invert_viewmats(self, viewmats: torch.Tensor) -> torch.Tensor:
        """Normalized world-to-camera [C,4,4] -> source world-to-camera [C,4,4] (for export)."""
        center = torch.as_tensor(self.center, dtype=viewmats.dtype, device=viewmats.device)
        out = viewmats.clone()
        out[..., :3, 3] = viewmats[..., :3, 3] / self.scale - viewmats[..., :3, :3] @ center
        return out


@dataclass
class Scene:
    """A loaded multi-view capture in normalized world coordinates (see module docstring for conventions).

    Attributes:
        name: scene name (preset name or folder name).
        root: the scene folder.
        layout: which layout it was read from: "colmap", "llff" or "transforms".
        image_names: C file names (relative to the image folder), sorted.
        images: [C,H,W,3] float32 RGB in [0,1].
        masks: [C,H,W] float32 in {0,1} (1 = object), or None.
        depths: [C,H,W] float32 depth along the optical axis (0 = no value), or None.
        depth_units: "scene" (true depth, in normalized scene units) or "relative" (monocular, arbitrary scale,
            e.g. ZoeDepth), or None when there are no depth maps.
        viewmats: [C,4,4] float32 world-to-camera (OpenCV axes), normalized world.
        Ks: [C,3,3] float32 pinhole intrinsics at (width, height).
        width, height: image size in pixels.
        splits: named view subsets, e.g. {"4": [...], "6": [...], "9": [...], "test": [...]}.
        split_sources: where each split came from (a file name, "preset" or "farthest-point").
        points: [P,3] float32 SfM points in normalized world, or None.
        point_colors: [P,3] float32 RGB in [0,1], or None.
        normalization: the source-to-normalized similarity (invert it for export).
        resolution: the image pyramid level read (images_{resolution}; 1 = full size).
        matches: feature matches between the views (`warpbags.correspondences`), found on the images as read and
            carried along when the scene is cut to some views or downscaled; None until `training_scene` finds them
            for a run that uses them.
    """

    name: str
    root: Path
    layout: str
    image_names: list[str]
    images: torch.Tensor
    masks: torch.Tensor | None
    depths: torch.Tensor | None
    depth_units: str | None
    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    splits: dict[str, list[int]] = field(default_factory=dict)
    split_sources: dict[str, str] = field(default_factory=dict)
    points: torch.Tensor | None = None
    point_colors: torch.Tensor | None = None
    normalization: SceneNormalization = field(default_factory=SceneNormalization)
    resolution: int = 1
    matches: ViewMatches | None = None

    @property
    def num_views(self) -> int:
        return len(self.image_names)

    def camera_centers(self) -> torch.Tensor:
        """[C,3] camera centres in normalized world."""
        return camera_centers(self.viewmats)

    def on_background(self, background: float | tuple[float, float, float]) -> torch.Tensor:
        """[C,H,W,3] the images with everything outside their masks replaced by `background` (a grey level or RGB):
        the object as training and evaluation compare it. Without masks, the images as they are."""
        if self.masks is None:
            return self.images
        masks = self.masks[..., None]
        background = torch.as_tensor(background, dtype=self.images.dtype, device=self.images.device)
        return self.images * masks + background * (1 - masks)

    def orbit_radius(self) -> float:
        """Mean distance of the camera centres from the world origin (the object centre)."""
        return float(self.camera_centers().norm(dim=-1).mean())

    def train_views(self, views: int) -> list[int]:
        """Indices of `views` training views: the split of that name, else a farthest-point choice.

        Raises:
            WarpbagsError: when the scene has fewer images than `views`.
        """
        if views < 1:
            raise WarpbagsError(f"--views must be at least 1, got {views}")
        if views > self.num_views:
            raise WarpbagsError(f"scene {self.name} has {self.num_views} images, fewer than --views {views}")
        if str(views) in self.splits:
            return list(self.splits[str(views)])
        # a view count without a split: farthest-point views among those not held out for testing
        test = set(self.splits.get("test", []))
        if views > self.num_views - len(test):
            raise WarpbagsError(f"scene {self.name} has {self.num_views - len(test)} images besides its {len(test)} "
                                f"test views, fewer than --views {views}")
        return farthest_views(self.camera_centers().double().numpy(), views, excluded=test)

    def subset(self, indices: list[int]) -> Scene:
        """A scene with only the given views (splits dropped, since their indices would no longer hold)."""
        index = torch.as_tensor(indices, dtype=torch.long)
        pick = lambda tensor: None if tensor is None else tensor[index]  # noqa: E731
        return replace(
            self,
            image_names=[self.image_names[i] for i in indices],
            images=self.images[index],
            masks=pick(self.masks),
            depths=pick(self.depths),
            viewmats=self.viewmats[index],
            Ks=self.Ks[index],
            splits={},
            split_sources={},
            matches=None if self.matches is None else self.matches.subset(indices),
        )


    def downscaled(self, max_size: int, keep_objects: bool = False) -> Scene:
        """The scene with images, masks, depths and intrinsics downscaled so the longer side is <= `max_size`.

        Images use area averaging; masks area averaging then a 0.5 threshold; depths nearest neighbour (0 stays
        "no value"). Intrinsics scale with the image edges (pixel centres at +0.5 stay consistent).

        Raises:
            WarpbagsError: with `keep_objects` (training), a view whose object mask thresholds empty: it would have
                no silhouette to fit.
        """
        if max_size <= 0 or max(self.width, self.height) <= max_size:
            return self
        factor = max_size / max(self.width, self.height)
        width, height = max(1, round(self.width * factor)), max(1, round(self.height * factor))

        def resize(tensor: torch.Tensor, interpolation: int) -> torch.Tensor:
            return torch.from_numpy(np.stack([cv2.resize(t.numpy(), (width, height), interpolation=interpolation) for t in tensor]))

        Ks = self.Ks.clone()
        Ks[:, 0, :] *= width / self.width
        Ks[:, 1, :] *= height / self.height
        masks = None if self.masks is None else (resize(self.masks, cv2.INTER_AREA) > 0.5).float()
        if keep_objects and masks is not None:  # no silhouette to fit: its distances would be unbounded (1e37)
            vanished = [name for name, before, after in zip(self.image_names, self.masks, masks)
                        if (before > 0.5).any() and not after.any()]
            if vanished:
                raise WarpbagsError(f"{self.root}: the object of view {vanished[0]} covers under half a pixel at "
                                    f"{width}x{height}, where its mask is empty: train at a larger --max-image-size "
                                    "or with fewer pyramid_levels")
        depths = None if self.depths is None else resize(self.depths, cv2.INTER_NEAREST)
        return replace(self, images=resize(self.images, cv2.INTER_AREA).clamp(0, 1), masks=masks, depths=depths,
                       Ks=Ks, width=width, height=height,
                       matches=None if self.matches is None else self.matches.scaled_to(width, height))


def farthest_views(camera_centers: np.ndarray, count: int, excluded: Container[int] = ()) -> list[int]:
    """Deterministic farthest-point sampling of viewing directions (from the mean camera centre of the views it
    chooses from), starting from the first of them. It reproduces the split files shipped with maryrose.

    Args:
        camera_centers: [C,3] camera centres.
        count: how many views to choose (<= C - len(excluded)).
        excluded: views never chosen (e.g. the test views); the others are chosen from as if they were all.

    Returns:
        `count` view indices (of all C views) in the order chosen (each set is a prefix of the next larger one).
    """
    candidates = [index for index in range(len(camera_centers)) if index not in excluded]
    if len(candidates) < len(camera_centers):
        return [candidates[pick] for pick in farthest_views(camera_centers[candidates], count)]
    directions = camera_centers - camera_centers.mean(0)
    directions = directions / np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    chosen = [0]
    angle_to_chosen = np.arccos(np.clip(directions @ directions[0], -1.0, 1.0))
    while len(chosen) < count:
        next_view = int(np.argmax(angle_to_chosen))
        chosen.append(next_view)
        angle_to_chosen = np.minimum(angle_to_chosen, np.arccos(np.clip(directions @ directions[next_view], -1, 1)))
    return chosen
