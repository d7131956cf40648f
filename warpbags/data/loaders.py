"""Read a scene folder in any of the supported layouts into a normalized `Scene`.

Layouts (detected in this order):
- COLMAP / MipNeRF360 / GaussianObject: `sparse/0/{cameras,images,points3D}.{bin,txt}` (or `sparse/`).
- LLFF: `poses_bounds.npy`, one row per image in sorted file-name order.
- nerfstudio / instant-ngp / Blender: `transforms.json` (OpenGL camera axes).

Shared by all: `images`, `images_2|4|8` (a missing downsampled folder is made from `images` in memory), `masks/`
(same stem, png or jpg, 255 or 1 = object, or the alpha channel, or a palette PNG's index above 0; without masks/,
the images' alpha channels), depth maps (`zoe_depth/*.png` 16-bit millimetres, or `depths/*.npy` in
scene units), split files `sparse_{4,6,9,test}.txt`.

This module detects the layout, assembles the `Scene` and normalizes it about the object centre; the camera
readers are in `layouts.py`, images/masks/depths in `images.py`, the split files in `splits.py`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import torch

from warpbags.cameras import camera_centers
from warpbags.data.images import (FACTORS, IMAGE_EXTENSIONS, IMAGE_MEMORY_BUDGET, default_resolution,
                                  factor_within_budget, image_size, mask_folder, masks_from_alphas, physical_memory,
                                  read_depths, read_images, read_masks, resolution_path, scene_bytes, undistort)
from warpbags.data.layouts import LayoutCameras, read_layout_cameras, scaled_intrinsics
from warpbags.data.scene import ORBIT_RADIUS, Scene, SceneNormalization
from warpbags.data.splits import read_splits
from warpbags.errors import WarpbagsError
from warpbags.silhouette import NEARLY_PARALLEL, rays_meeting_point

logger = logging.getLogger("warpbags.data")


def load_scene(
    root: str | Path,
    *,
    resolution: int | None = None,
    name: str | None = None,
    normalize: bool = True,
    default_splits: dict[str, list[int]] | None = None,
    load_depths: bool = True,
) -> Scene:
    """Load a scene folder.

    Args:
        root: the scene folder.
        resolution: downsampling factor 1, 2, 4 or 8 (reads `images_{r}`, or downsamples `images`); None picks
            `images` if present, else the first of `images_2|4|8` that exists.
        name: display name (default: the folder name).
        normalize: centre on the object and scale to `ORBIT_RADIUS` (see `SceneNormalization`).
        default_splits: splits to use when their `sparse_{key}.txt` is missing (e.g. published ones).
        load_depths: read depth maps when present.

    Returns:
        The `Scene`; its `normalization` maps source coordinates to the scene's.

    Raises:
        WarpbagsError: missing or unreadable files, inconsistent sizes, bad split indices.
    """
    root = Path(root)
    if not root.is_dir():
        raise WarpbagsError(f"scene folder {root} does not exist")
    cameras = read_layout_cameras(root)
    if unposed := _images_without_a_camera(root, cameras):
        logger.warning("%s: %d image(s) in images/ have no camera in its %s poses (e.g. %s): left out (images SfM did "
                       "not register?)", root, len(unposed), cameras.layout, unposed[0].relative_to(root))
    resolution = _resolution(root, cameras, resolution)
    image_files = [resolution_path(root, path, resolution) for path in cameras.image_paths]
    images, alphas, width, height = read_images(image_files, cameras.image_paths, resolution,
                                                alpha_masks=mask_folder(root, resolution) is None)
    # one scale takes each calibration to the images, each side within a pixel (the rounding of a reduced size,
    # whichever way a tool rounds); a tolerance of 1% of the height took a 3000 px photo cropped by 30 rows
    (calibrated_widths, calibrated_heights) = cameras.calibration_sizes.T
    lowest_scales = np.maximum((width - 1) / calibrated_widths, (height - 1) / calibrated_heights)
    highest_scales = np.minimum((width + 1) / calibrated_widths, (height + 1) / calibrated_heights)
    skewed = np.flatnonzero(lowest_scales > highest_scales)
    if len(skewed):
        calibrated = cameras.calibration_sizes[skewed[0]]
        raise WarpbagsError(f"image {image_files[skewed[0]]} is {width}x{height}, its camera is calibrated at "
                            f"{calibrated[0]:g}x{calibrated[1]:g}: another shape (rotated or cropped?)")
    Ks = scaled_intrinsics(cameras.Ks, cameras.calibration_sizes, np.array([width, height]))

    masks = read_masks(root, cameras.image_names, width, height, resolution)
    if masks is None and alphas is not None:
        masks = masks_from_alphas(alphas, image_files)
    if masks is not None:
        _warn_of_background_masks(root, masks, cameras.image_names)
    depths, depth_units = (None, None)
    if load_depths:
        depths, depth_units = read_depths(root, cameras.image_names, width, height)

    if np.any(cameras.distortions != 0):
        undistort(images, masks, depths, Ks, cameras.distortions)
        logger.warning("%s: undistorted %d images with OpenCV (distorted camera model)", root, len(images))

    normalization = SceneNormalization.identity()
    if normalize:
        center = object_center(cameras.viewmats, Ks, masks, cameras.points)
        centers = camera_centers(torch.from_numpy(cameras.viewmats)).numpy()
        mean_radius = float(np.linalg.norm(centers - center, axis=1).mean())
        if not mean_radius > 0:
            raise WarpbagsError(f"{root}: all cameras sit at the object centre, cannot normalize")
        normalization = SceneNormalization(tuple(float(v) for v in center), ORBIT_RADIUS / mean_radius)

    viewmats = normalization.apply_viewmats(torch.from_numpy(cameras.viewmats)).float()
    points = colors = None
    if cameras.points is not None and len(cameras.points):
        points = normalization.apply_points(torch.from_numpy(cameras.points)).float()
        colors = torch.from_numpy(cameras.colors.astype(np.float32) / 255.0)
    depth_tensor = None
    if depths is not None:
        depth_tensor = torch.from_numpy(depths)
        if depth_units == "scene":
            depth_tensor = depth_tensor * normalization.scale

    scene = Scene(
        name=name or root.name,
        root=root,
        layout=cameras.layout,
        image_names=cameras.image_names,
        images=torch.from_numpy(images),
        masks=None if masks is None else torch.from_numpy(masks),
        depths=depth_tensor,
        depth_units=depth_units,
        viewmats=viewmats,
        Ks=torch.from_numpy(Ks).float(),
        width=width,
        height=height,
        points=points,
        point_colors=colors,
        normalization=normalization,
        resolution=resolution,
    )
    scene.splits, scene.split_sources = read_splits(root, scene, default_splits, cameras.test_names)
    return scene


def _warn_of_background_masks(root: Path, masks: np.ndarray, names: list[str]) -> None:
    """Say where the masks look like something else than an object's silhouette: most of the image border marked
    as object in most views (inverted masks, or crop masks such as nerfstudio's, which mark the pixels to train on),
    or a view marked as object everywhere (no silhouette). Both trained without a word, the poses far off."""
    borders = np.concatenate([masks[:, 0], masks[:, -1], masks[:, 1:-1, 0], masks[:, 1:-1, -1]], axis=1)
    object_borders = borders.mean(axis=1) > 0.5
    if object_borders.mean() > 0.5:
        logger.warning("%s: the masks of %d of %d views mark most of the image border as object (e.g. %s): a mask "
                       "marks the object (white) on the background (black); inverted or crop masks train the "
                       "silhouettes wrong", root, object_borders.sum(), len(masks), names[np.argmax(object_borders)])
    elif (whole := masks.reshape(len(masks), -1).all(axis=1)).any():
        logger.warning("%s: the mask of %s marks every pixel as object: that view holds no silhouette", root,
                       names[np.argmax(whole)])


def _images_without_a_camera(root: Path, cameras: LayoutCameras) -> list[Path]:
    """The image files under `root`/images that no camera of `cameras` names (hidden files, such as macOS's "._"
    copies, are not images)."""
    folder = root / "images"
    if not folder.is_dir():
        return []
    named = {Path(os.path.normpath(path)) for path in cameras.image_paths}
    return sorted(path for path in folder.rglob("*") if path.suffix.lower() in IMAGE_EXTENSIONS
                  and not path.name.startswith(".") and path.is_file() and Path(os.path.normpath(path)) not in named)


def _resolution(root: Path, cameras: LayoutCameras, asked: int | None) -> int:
    """The factor to read `cameras`' images at: `asked`, else the scene's default (`images_2|4|8/` when only that
    exists) coarsened until every view fits `IMAGE_MEMORY_BUDGET`, so that a folder of full-size photographs loads
    at a fraction of its size instead of exhausting memory.

    Raises:
        WarpbagsError: a factor other than 1, 2, 4, 8, or one whose images would not fit this machine's memory.
    """
    if asked is not None and asked not in FACTORS:
        raise WarpbagsError(f"resolution must be 1, 2, 4 or 8, got {asked}")
    if not cameras.image_paths:
        raise WarpbagsError(f"no images in {root}: its {cameras.layout} cameras name none")
    factor = checked = asked or (1 if cameras.layout == "transforms" else default_resolution(root))
    _require_image_folder(root, cameras, checked)
    first = resolution_path(root, cameras.image_paths[0], factor)
    width, height = image_size(first)
    if first != cameras.image_paths[0]:  # read from images_{factor}/: the full size is factor times its own
        width, height = width * factor, height * factor
    count = len(cameras.image_paths)
    if asked is None and scene_bytes(count, width, height, factor) > IMAGE_MEMORY_BUDGET:
        fitting = max(factor, factor_within_budget(count, width, height, IMAGE_MEMORY_BUDGET))
        logger.warning("%s: %d images of %dx%d px: read at 1/%d (%dx%d), as at full size they would take %.1f GiB "
                       "(--resolution sets the factor)", root, count, width, height, fitting, round(width / fitting),
                       round(height / fitting), scene_bytes(count, width, height, 1) / 1024**3)
        factor = fitting
    memory = physical_memory()
    if memory is not None and scene_bytes(count, width, height, factor) > memory:
        raise WarpbagsError(f"{root}: {count} images of {width}x{height} px at resolution {factor} take "
                            f"{scene_bytes(count, width, height, factor) / 1024**3:.1f} GiB, more than this machine's "
                            f"{memory / 1024**3:.1f} GiB: choose a coarser --resolution (2, 4 or 8)")
    if factor != checked:  # coarsened to fit the memory budget: that factor's folder too
        _require_image_folder(root, cameras, factor)
    return factor


def _require_image_folder(root: Path, cameras: LayoutCameras, factor: int) -> None:
    """An `images_{factor}/` or `images/` folder to read a COLMAP or LLFF scene at `factor` from (a transforms.json
    names its images' paths itself); said with the folders the scene has, not as the first image missing."""
    wanted = (f"images_{factor}", "images")
    if cameras.layout != "transforms" and not any((root / folder).is_dir() for folder in wanted):
        folders = sorted(f"{path.name}/" for path in root.glob("images*") if path.is_dir())
        raise WarpbagsError(f"no images_{factor}/ or images/ folder in {root} (resolution {factor}); it has "
                            f"{', '.join(folders) or 'no image folder'}")


def object_center(
    viewmats: np.ndarray, Ks: np.ndarray, masks: np.ndarray | None = None, points: np.ndarray | None = None
) -> np.ndarray:
    """The point closest (least squares) to the rays through the mask centroids, or the optical axes without masks.

    Args:
        viewmats: [C,4,4] world-to-camera.
        Ks: [C,3,3] intrinsics at the masks' resolution.
        masks: [C,H,W] object masks, or None.
        points: [P,3] SfM points, the fallback (median) when the rays are near parallel (forward-facing captures);
            without them, the mean camera centre. Either fallback is logged as a warning.

    Returns:
        [3] float64 object centre in the viewmats' world.
    """
    pixels = Ks[:, :2, 2].copy()
    if masks is not None:
        for index, mask in enumerate(masks):
            rows, cols = np.nonzero(mask > 0.5)
            if len(rows):
                pixels[index] = cols.mean() + 0.5, rows.mean() + 0.5
    rays_camera = np.linalg.solve(Ks, np.concatenate([pixels, np.ones((len(Ks), 1))], axis=1)[:, :, None])[..., 0]
    directions = np.einsum("cji,cj->ci", viewmats[:, :3, :3], rays_camera)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = camera_centers(torch.from_numpy(viewmats))
    center = rays_meeting_point(origins, torch.from_numpy(directions), min_spread=NEARLY_PARALLEL)
    if center is not None:
        return center.numpy()
    if points is not None and len(points):
        logger.warning("object centre: the views' rays through the object are nearly parallel (forward-facing "
                       "capture?); using the median of the %d SfM points instead", len(points))
        return np.median(points, axis=0)
    logger.warning("object centre: the views' rays through the object are nearly parallel (forward-facing "
                   "capture?) and there are no SfM points; using the mean camera centre instead")
    return origins.numpy().mean(0)
