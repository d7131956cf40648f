"""Read a scene folder in any of the supported layouts into a normalized `Scene`.

Layouts (detected in this order):
- COLMAP / MipNeRF360 / GaussianObject: `sparse/0/{cameras,images,points3D}.{bin,txt}` (or `sparse/`).
- LLFF: `poses_bounds.npy`, one row per image in sorted file-name order.
- nerfstudio / instant-ngp / Blender: `transforms.json` (OpenGL camera axes).

Shared by all: `images`, `images_2|4|8` (a missing downsampled folder is made from `images` in memory), `masks/`
(same stem, png or jpg, 255 = object), depth maps (`zoe_depth/*.png` 16-bit millimetres, or `depths/*.npy` in
scene units), split files `sparse_{4,6,9,test}.txt`.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from warpbags.cameras import camera_centers
from warpbags.data.colmap import read_model
from warpbags.data.scene import DEFAULT_SPLIT_SIZES, ORBIT_RADIUS, Scene, SceneNormalization, farthest_views
from warpbags.errors import WarpbagsError
from warpbags.silhouette import rays_meeting_point

logger = logging.getLogger("warpbags.data")

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
TEST_EVERY = 8
"""Without `sparse_test.txt`, every 8th view not used for training is a test view (the MipNeRF360 hold-out)."""

# OpenGL (x right, y up, z back) camera axes to OpenCV (x right, y down, z forward): flip y and z.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class _Cameras:
    """Camera data from a layout, before images are read: everything at the calibration resolution."""

    layout: str
    image_paths: list[Path]  # full-resolution image files (may not exist when only a downsampled folder does)
    image_names: list[str]
    viewmats: np.ndarray  # [C,4,4] float64 world-to-camera, OpenCV axes
    Ks: np.ndarray  # [C,3,3] float64 at calibration sizes
    calibration_sizes: np.ndarray  # [C,2] (width, height) the Ks refer to
    distortions: np.ndarray  # [C,4] OpenCV k1, k2, p1, p2
    points: np.ndarray | None = None
    colors: np.ndarray | None = None
    test_names: set[str] | None = None


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
    if (root / "sparse" / "0").is_dir() or (root / "sparse" / "cameras.bin").is_file():
        cameras = _colmap_cameras(root)
    elif (root / "poses_bounds.npy").is_file():
        cameras = _llff_cameras(root)
    elif (root / "transforms.json").is_file() or (root / "transforms_train.json").is_file():
        cameras = _transforms_cameras(root)
    else:
        raise WarpbagsError(
            f"no cameras in {root}: expected sparse/0/cameras.bin (COLMAP), poses_bounds.npy (LLFF) or transforms.json"
        )
    if resolution is None and cameras.layout != "transforms":
        resolution = _default_resolution(root)
    resolution = resolution or 1
    if resolution not in (1, 2, 4, 8):
        raise WarpbagsError(f"resolution must be 1, 2, 4 or 8, got {resolution}")

    image_folders = (f"images_{resolution}", "images")
    if cameras.layout != "transforms" and not any((root / folder).is_dir() for folder in image_folders):
        raise WarpbagsError(f"no images_{resolution}/ or images/ folder in {root} (resolution {resolution})")
    image_files = [_resolution_path(root, path, resolution) for path in cameras.image_paths]
    images, alphas, width, height = _read_images(image_files, cameras.image_paths, resolution)
    Ks = cameras.Ks.copy()
    Ks[:, 0, :] *= (width / cameras.calibration_sizes[:, 0])[:, None]
    Ks[:, 1, :] *= (height / cameras.calibration_sizes[:, 1])[:, None]

    masks = _read_masks(root, cameras.image_names, width, height, resolution)
    if masks is None and alphas is not None:
        masks = (alphas > 0.5).astype(np.float32)
    depths, depth_units = (None, None)
    if load_depths:
        depths, depth_units = _read_depths(root, cameras.image_names, width, height)

    if np.any(cameras.distortions != 0):
        _undistort(images, masks, depths, Ks, cameras.distortions)
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
    scene.splits, scene.split_sources = _read_splits(root, scene, default_splits, cameras.test_names)
    return scene


# ---------------------------------------------------------------------------------------------------------------
# Layouts


def _colmap_cameras(root: Path) -> _Cameras:
    model_dir = root / "sparse" / "0" if (root / "sparse" / "0").is_dir() else root / "sparse"
    model = read_model(model_dir)
    return _Cameras(
        layout="colmap",
        image_paths=[root / "images" / name for name in model.image_names],
        image_names=model.image_names,
        viewmats=model.viewmats,
        Ks=np.stack([camera.K for camera in model.cameras]),
        calibration_sizes=np.array([[camera.width, camera.height] for camera in model.cameras], dtype=np.float64),
        distortions=np.stack([camera.distortion for camera in model.cameras]),
        points=model.points,
        colors=model.colors,
    )


def _llff_cameras(root: Path) -> _Cameras:
    """`poses_bounds.npy`: per image [R | t | hwf] 3x5 camera-to-world, columns (down, right, back), then near/far."""
    path = root / "poses_bounds.npy"
    try:
        poses_bounds = np.load(path)
    except (OSError, ValueError) as error:
        raise WarpbagsError(f"cannot read {path}: {error}") from None
    if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
        raise WarpbagsError(f"{path} has shape {poses_bounds.shape}, expected [N,17]")
    image_dir = _first_existing_image_dir(root)
    names = sorted(p.name for p in image_dir.iterdir() if p.suffix in IMAGE_EXTENSIONS)
    if len(names) != len(poses_bounds):
        raise WarpbagsError(f"{path} has {len(poses_bounds)} poses but {image_dir} holds {len(names)} images")
    matrices = poses_bounds[:, :15].reshape(-1, 3, 5)
    down, right, back = matrices[:, :, 0], matrices[:, :, 1], matrices[:, :, 2]
    camera_to_world = np.tile(np.eye(4), (len(names), 1, 1))
    camera_to_world[:, :3, 0] = right
    camera_to_world[:, :3, 1] = down
    camera_to_world[:, :3, 2] = -back
    camera_to_world[:, :3, 3] = matrices[:, :, 3]
    height, width, focal = matrices[:, 0, 4], matrices[:, 1, 4], matrices[:, 2, 4]
    Ks = np.zeros((len(names), 3, 3))
    Ks[:, 0, 0] = Ks[:, 1, 1] = focal
    Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = width / 2, height / 2, 1.0
    return _Cameras(
        layout="llff",
        image_paths=[root / "images" / name for name in names],
        image_names=names,
        viewmats=np.linalg.inv(camera_to_world),
        Ks=Ks,
        calibration_sizes=np.stack([width, height], axis=1),
        distortions=np.zeros((len(names), 4)),
    )


def _transforms_cameras(root: Path) -> _Cameras:
    """nerfstudio / instant-ngp `transforms.json` or Blender `transforms_{train,val,test}.json` (OpenGL axes)."""
    if (root / "transforms.json").is_file():
        sources = [root / "transforms.json"]
    else:
        sources = [root / f"transforms_{part}.json" for part in ("train", "val", "test")]
        sources = [path for path in sources if path.is_file()]
    frames, test_names = [], set()
    for path in sources:
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise WarpbagsError(f"cannot read {path}: {error}") from None
        if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
            raise WarpbagsError(f"{path} has no 'frames' list")
        for frame in meta["frames"]:
            frames.append((path, meta, frame))
            if path.name == "transforms_test.json":
                test_names.add(_frame_name(root, frame, path))
    rows = []
    for path, meta, frame in frames:
        name = _frame_name(root, frame, path)
        image_path = root / name
        merged = {**meta, **frame}
        try:
            camera_to_world = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (KeyError, ValueError, TypeError):
            raise WarpbagsError(f"{path}: frame {name} has no valid transform_matrix") from None
        if camera_to_world.shape not in ((4, 4), (3, 4)):
            raise WarpbagsError(f"{path}: frame {name} transform_matrix has shape {camera_to_world.shape}")
        camera_to_world = np.vstack([camera_to_world[:3], [0, 0, 0, 1]]) @ OPENGL_TO_OPENCV
        width, height = merged.get("w"), merged.get("h")
        if width is None or height is None:
            probe = cv2.imread(str(_resolution_path(root, image_path, 1)), cv2.IMREAD_UNCHANGED)
            if probe is None:
                raise WarpbagsError(f"image {image_path} (named in {path.name}) is missing or unreadable")
            height, width = probe.shape[:2]
        if "fl_x" in merged:
            fx = float(merged["fl_x"])
            fy = float(merged.get("fl_y", fx))
        elif "camera_angle_x" in merged:
            fx = 0.5 * width / math.tan(0.5 * float(merged["camera_angle_x"]))
            fy = 0.5 * height / math.tan(0.5 * float(merged["camera_angle_y"])) if "camera_angle_y" in merged else fx
        else:
            raise WarpbagsError(f"{path}: no focal length (fl_x or camera_angle_x)")
        K = np.array([[fx, 0, merged.get("cx", width / 2)], [0, fy, merged.get("cy", height / 2)], [0, 0, 1]], float)
        distortion = np.array([merged.get(key, 0.0) for key in ("k1", "k2", "p1", "p2")], dtype=np.float64)
        if any(merged.get(key, 0.0) for key in ("k3", "k4")):
            raise WarpbagsError(f"{path}: k3/k4 distortion is not supported (undistort the images first)")
        rows.append((name, image_path, np.linalg.inv(camera_to_world), K, (width, height), distortion))
    rows.sort(key=lambda row: row[0])
    return _Cameras(
        layout="transforms",
        image_paths=[row[1] for row in rows],
        image_names=[row[0] for row in rows],
        viewmats=np.stack([row[2] for row in rows]),
        Ks=np.stack([row[3] for row in rows]),
        calibration_sizes=np.array([row[4] for row in rows], dtype=np.float64),
        distortions=np.stack([row[5] for row in rows]),
        test_names=test_names or None,
    )


def _frame_name(root: Path, frame: dict, source: Path) -> str:
    if "file_path" not in frame:
        raise WarpbagsError(f"{source}: a frame has no file_path")
    relative = Path(str(frame["file_path"]))
    if not relative.suffix:  # Blender writes "./train/r_0" for "./train/r_0.png"
        relative = relative.with_suffix(".png")
    return (root / relative).resolve().relative_to(root.resolve()).as_posix()


# ---------------------------------------------------------------------------------------------------------------
# Images, masks, depth maps


def _default_resolution(root: Path) -> int:
    if (root / "images").is_dir():
        return 1
    for factor in (2, 4, 8):
        if (root / f"images_{factor}").is_dir():
            return factor
    raise WarpbagsError(f"no image folder in {root}: expected images/ or images_2|4|8/")


def _first_existing_image_dir(root: Path) -> Path:
    factor = _default_resolution(root)
    return root / ("images" if factor == 1 else f"images_{factor}")


def _resolution_path(root: Path, full_path: Path, resolution: int) -> Path:
    """The file to read for `full_path` at `resolution`: `images_{r}/...` if present, else the full-size one."""
    if resolution == 1:
        return full_path
    relative = full_path.relative_to(root)
    if relative.parts and relative.parts[0] == "images":
        downsampled = root.joinpath(f"images_{resolution}", *relative.parts[1:])
        if downsampled.is_file():
            return downsampled
        if downsampled.with_suffix(".png").is_file():  # some tools convert to png when downsampling
            return downsampled.with_suffix(".png")
    return full_path


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if image is None:
        if path.is_file():
            raise WarpbagsError(f"image {path} is unreadable")
        raise WarpbagsError(f"image {path} is missing (named by the camera file)")
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    image = image.astype(np.float32) / scale
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    channels = image.shape[2]
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2RGB)


def _read_images(
    files: list[Path], full_paths: list[Path], resolution: int
) -> tuple[np.ndarray, np.ndarray | None, int, int]:
    """Read all images; resize those read at full size to 1/resolution. Returns images, alphas, width, height."""
    images = alphas = None
    width = height = 0
    for index, (path, full_path) in enumerate(zip(files, full_paths)):
        image = _read_image(path)
        if path == full_path and resolution > 1:
            target = (round(image.shape[1] / resolution), round(image.shape[0] / resolution))
            image = cv2.resize(image, target, interpolation=cv2.INTER_AREA)
        if images is None:
            height, width = image.shape[:2]
            images = np.empty((len(files), height, width, 3), dtype=np.float32)
            if image.shape[2] == 4:
                alphas = np.empty((len(files), height, width), dtype=np.float32)
        if image.shape[:2] != (height, width):
            raise WarpbagsError(
                f"image {path} is {image.shape[1]}x{image.shape[0]}, the others are {width}x{height}"
            )
        images[index] = image[:, :, :3]
        if alphas is not None:
            alphas[index] = image[:, :, 3] if image.shape[2] == 4 else 1.0
    return images, alphas, width, height


def _find_by_stem(folder: Path, name: str, extensions: tuple[str, ...]) -> Path | None:
    """`folder/<stem><ext>`, trying the name with its sub-folders, then the bare file name (transforms.json
    names such as images/frame_001.png look up masks/frame_001.png), then `<name><ext>` (frame_001.png.png)."""
    relative = Path(name)
    stems = [relative.with_suffix(""), Path(relative.stem), relative]
    for extension in extensions:
        for stem in stems:
            candidate = folder / f"{stem}{extension}"
            if candidate.is_file():
                return candidate
    return None


def _resize_to(array: np.ndarray, width: int, height: int, path: Path, what: str, nearest: bool) -> np.ndarray:
    """Accept `array` at (width, height) or at an integer multiple of it (another resolution); else raise."""
    found_height, found_width = array.shape[:2]
    if (found_width, found_height) == (width, height):
        return array
    factor_x, factor_y = found_width / width, found_height / height
    same_aspect = abs(factor_x - factor_y) <= 0.02 * factor_x and factor_x >= 1.0
    if not same_aspect or abs(factor_x - round(factor_x)) > 0.02:
        raise WarpbagsError(f"{what} {path} is {found_width}x{found_height}, its image is {width}x{height}")
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(array, (width, height), interpolation=interpolation)


def _read_masks(root: Path, names: list[str], width: int, height: int, resolution: int) -> np.ndarray | None:
    folder = root / f"masks_{resolution}" if (root / f"masks_{resolution}").is_dir() else root / "masks"
    if not folder.is_dir():
        return None
    masks = np.empty((len(names), height, width), dtype=np.float32)
    for index, name in enumerate(names):
        path = _find_by_stem(folder, name, (".png", ".jpg", ".jpeg", ".JPG", ".PNG"))
        if path is None:
            raise WarpbagsError(f"mask for image {name} is missing: expected {folder / Path(name).stem}.png or .jpg")
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise WarpbagsError(f"mask {path} is unreadable")
        mask = _resize_to(mask.astype(np.float32) / 255.0, width, height, path, "mask", nearest=False)
        masks[index] = mask >= 0.5
    return masks


def _read_depths(root: Path, names: list[str], width: int, height: int) -> tuple[np.ndarray | None, str | None]:
    """`depths/*.npy` (scene units) or `zoe_depth/*.png` (16-bit millimetres, monocular: relative)."""
    for folder, extension, units in ((root / "depths", ".npy", "scene"), (root / "zoe_depth", ".png", "relative")):
        if not folder.is_dir():
            continue
        depths = np.empty((len(names), height, width), dtype=np.float32)
        for index, name in enumerate(names):
            path = _find_by_stem(folder, name, (extension,))
            if path is None:
                expected = folder / f"{Path(name).stem}{extension}"
                raise WarpbagsError(f"depth map for image {name} is missing: expected {expected}")
            if extension == ".npy":
                try:
                    depth = np.load(path).astype(np.float32)
                except (OSError, ValueError) as error:
                    raise WarpbagsError(f"cannot read depth map {path}: {error}") from None
            else:
                raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                if raw is None or raw.ndim != 2:
                    raise WarpbagsError(f"depth map {path} is not a single-channel 16-bit PNG")
                depth = raw.astype(np.float32) / 1000.0
            depth = np.squeeze(depth)
            if depth.ndim != 2:
                raise WarpbagsError(f"depth map {path} has shape {depth.shape}, expected [H,W]")
            depths[index] = _resize_to(depth, width, height, path, "depth map", nearest=True)
        return depths, units
    return None, None


def _undistort(
    images: np.ndarray, masks: np.ndarray | None, depths: np.ndarray | None, Ks: np.ndarray, distortions: np.ndarray
) -> None:
    """Undistort in place to the same pinhole K (OpenCV's pixel centres are at integers: shift by 0.5)."""
    height, width = images.shape[1:3]
    for index in range(len(images)):
        if not np.any(distortions[index]):
            continue
        K_opencv = Ks[index].copy()
        K_opencv[:2, 2] -= 0.5
        map_x, map_y = cv2.initUndistortRectifyMap(
            K_opencv, distortions[index], None, K_opencv, (width, height), cv2.CV_32FC1
        )
        images[index] = cv2.remap(images[index], map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if masks is not None:
            masks[index] = cv2.remap(masks[index], map_x, map_y, cv2.INTER_NEAREST)
        if depths is not None:
            depths[index] = cv2.remap(depths[index], map_x, map_y, cv2.INTER_NEAREST)


# ---------------------------------------------------------------------------------------------------------------
# Object centre and splits


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
    center = rays_meeting_point(origins, torch.from_numpy(directions), min_spread=1e-3)
    if center is not None:
        return center.numpy()
    if points is not None and len(points):
        logger.warning("object centre: the views' rays through the object are nearly parallel (forward-facing "
                       "capture?); using the median of the %d SfM points instead", len(points))
        return np.median(points, axis=0)
    logger.warning("object centre: the views' rays through the object are nearly parallel (forward-facing "
                   "capture?) and there are no SfM points; using the mean camera centre instead")
    return origins.numpy().mean(0)


def read_split_file(path: Path, num_views: int) -> list[int]:
    """0-based view indices, one per line (blank lines ignored)."""
    indices = []
    for line_number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            index = int(line.strip())
        except ValueError:
            raise WarpbagsError(f"{path}:{line_number}: {line.strip()!r} is not a view index") from None
        if not 0 <= index < num_views:
            raise WarpbagsError(f"{path}:{line_number}: view index {index} out of range for {num_views} images")
        indices.append(index)
    return indices


def _read_splits(
    root: Path, scene: Scene, default_splits: dict[str, list[int]] | None, test_names: set[str] | None
) -> tuple[dict[str, list[int]], dict[str, str]]:
    splits, sources = {}, {}
    for path in sorted(root.glob("sparse_*.txt")):
        key = path.stem.removeprefix("sparse_")
        splits[key], sources[key] = read_split_file(path, scene.num_views), path.name
    for key, indices in (default_splits or {}).items():
        if key in splits:
            continue
        bad = [index for index in indices if not 0 <= index < scene.num_views]
        if bad:
            raise WarpbagsError(
                f"split {key} of scene {scene.name}: view index {bad[0]} out of range for {scene.num_views} images"
            )
        splits[key], sources[key] = list(indices), "preset"
        logger.warning("%s: sparse_%s.txt missing, using the published split %s", scene.name, key, indices)
    centers = scene.camera_centers().double().numpy()
    for size in DEFAULT_SPLIT_SIZES:
        if str(size) in splits or size > scene.num_views:
            continue
        splits[str(size)] = sorted(farthest_views(centers, size))
        sources[str(size)] = "farthest-point"
        logger.warning("%s: sparse_%d.txt missing, farthest-point views %s", scene.name, size, splits[str(size)])
    if "test" not in splits:
        if test_names:
            splits["test"] = [i for i, name in enumerate(scene.image_names) if name in test_names]
            sources["test"] = "transforms_test.json"
        else:
            train = {index for key, indices in splits.items() for index in indices}
            splits["test"] = [i for i in range(0, scene.num_views, TEST_EVERY) if i not in train]
            sources["test"] = f"every {TEST_EVERY}th"
            logger.warning("%s: sparse_test.txt missing, test views %s", scene.name, splits["test"])
    return splits, sources
