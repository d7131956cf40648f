"""Camera readers, one per scene-folder layout, each returning a layout's cameras before images are read.

- COLMAP / MipNeRF360 / GaussianObject: `sparse/0/{cameras,images,points3D}.{bin,txt}` (or `sparse/`).
- LLFF: `poses_bounds.npy`, one row per image in sorted file-name order.
- nerfstudio / instant-ngp / Blender: `transforms.json` (OpenGL camera axes).
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from warpbags.cameras import improper_viewmats
from warpbags.data.colmap import read_model
from warpbags.data.images import FACTORS, IMAGE_EXTENSIONS, first_existing_image_dir, image_size, resolution_path
from warpbags.errors import WarpbagsError
from warpbags.files import read_array

logger = logging.getLogger("warpbags.data")

# OpenGL (x right, y up, z back) camera axes to OpenCV (x right, y down, z forward): flip y and z.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class LayoutCameras:
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


def scaled_intrinsics(Ks: np.ndarray, calibration_sizes: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """[C,3,3] intrinsics calibrated at [C,2] (width, height) `calibration_sizes`, for images of `sizes` ([C,2], or
    one (width, height) for all): the first row scaled by the widths' ratio, the second by the heights'."""
    scaled = Ks.copy()
    scaled[:, :2, :] *= (np.asarray(sizes, dtype=np.float64) / calibration_sizes)[:, :, None]
    return scaled


def read_layout_cameras(root: Path) -> LayoutCameras:
    """The cameras of scene folder `root`, from whichever layout it holds (COLMAP first, then LLFF, then
    transforms.json).

    Raises:
        WarpbagsError: no layout's camera file, or one that cannot be read.
    """
    if (root / "sparse" / "0").is_dir() or any((root / "sparse" / name).is_file() for name in ("cameras.bin",
                                                                                             "cameras.txt")):
        return _proper(colmap_cameras(root), root / "sparse")
    if (root / "poses_bounds.npy").is_file():
        return _proper(llff_cameras(root), root / "poses_bounds.npy")
    if (root / "transforms.json").is_file() or (root / "transforms_train.json").is_file():
        return _proper(transforms_cameras(root), root / "transforms*.json")
    raise WarpbagsError(
        f"no cameras in {root}: expected sparse/0/cameras.bin (COLMAP), poses_bounds.npy (LLFF) or transforms.json"
    )


def _proper(cameras: LayoutCameras, source: Path) -> LayoutCameras:
    """`cameras`, whose poses must each be a rotation and a translation (`improper_viewmats`): a scaled or sheared
    matrix would train as a wrong camera, and every reader of the run would refuse its poses afterwards; and whose
    calibrations must be finite with positive focal lengths and image sizes (a negative focal length trained to
    nonsense, a NaN one failed deep in linear algebra).

    Raises:
        WarpbagsError: one is not, named by its image and `source`, the file it came from.
    """
    improper = improper_viewmats(torch.from_numpy(cameras.viewmats)).tolist()
    if improper:
        raise WarpbagsError(f"{source}: the pose of {cameras.image_names[improper[0]]} is not a rotation and a "
                            "translation (scaled, sheared, mirrored or not finite)")
    for name, K, size, distortion in zip(cameras.image_names, cameras.Ks, cameras.calibration_sizes,
                                         cameras.distortions):
        if not (np.isfinite(K).all() and np.isfinite(distortion).all() and np.isfinite(size).all()
                and K[0, 0] > 0 and K[1, 1] > 0 and (size > 0).all()):
            raise WarpbagsError(f"{source}: the calibration of {name} is not a camera's (its intrinsics and distortion "
                                f"must be finite, its focal lengths and image size > 0; got fx {K[0, 0]:g}, fy "
                                f"{K[1, 1]:g}, cx {K[0, 2]:g}, cy {K[1, 2]:g}, distortion "
                                f"{', '.join(f'{value:g}' for value in distortion)}, {size[0]:g} x {size[1]:g})")
    return cameras


def colmap_cameras(root: Path) -> LayoutCameras:
    """`sparse/0/` (or `sparse/`) read through pycolmap, with its SfM points."""
    model_dir = root / "sparse" / "0" if (root / "sparse" / "0").is_dir() else root / "sparse"
    model = read_model(model_dir)
    return LayoutCameras(
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


def llff_cameras(root: Path) -> LayoutCameras:
    """`poses_bounds.npy`: per image [R | t | hwf] 3x5 camera-to-world, columns (down, right, back), then near/far."""
    path = root / "poses_bounds.npy"
    poses_bounds = read_array(path, "LLFF poses")
    if poses_bounds.ndim != 2 or poses_bounds.shape[1] != 17:
        raise WarpbagsError(f"{path} has shape {poses_bounds.shape}, expected [N,17]")
    image_dir = first_existing_image_dir(root)
    names = sorted(p.name for p in image_dir.iterdir()  # hidden files such as macOS's "._" copies are not images
                   if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith("."))
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
    return LayoutCameras(
        layout="llff",
        image_paths=[root / "images" / name for name in names],
        image_names=names,
        viewmats=np.linalg.inv(camera_to_world),
        Ks=Ks,
        calibration_sizes=np.stack([width, height], axis=1),
        distortions=np.zeros((len(names), 4)),
    )


# The camera models of a transforms.json that warpbags reads, nerfstudio's perspective ones: pinhole, with k1, k2,
# p1, p2 (fisheye and equirectangular cameras project otherwise, and would be taken for a distorted pinhole).
TRANSFORMS_CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def transforms_cameras(root: Path) -> LayoutCameras:
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
        if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
            raise WarpbagsError(f"{path} has no 'frames' list")
        if not meta["frames"]:
            raise WarpbagsError(f"{path}: its 'frames' list is empty")
        for frame in meta["frames"]:
            frames.append((path, meta, frame))
            if path.name == "transforms_test.json":
                test_names.add(_frame_name(root, frame, path))
        # nerfstudio's per-frame masks mark the pixels to train on, not an object, and its depth files have its own
        # units: neither is what warpbags reads, so a scene that names them is told where its own files go
        for key, place in (("mask_path", "object masks in masks/<image name>"),
                           ("depth_file_path", "depth maps in depths/<image stem>.npy or zoe_depth/<image stem>.png")):
            if any(isinstance(frame, dict) and key in frame for frame in meta["frames"]):
                logger.warning("%s: its frames' %s files are not read (warpbags reads %s)", path, key, place)
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
        number = functools.partial(_frame_number, path, name, merged)
        model = merged.get("camera_model") or "OPENCV"  # nerfstudio's default; null as absent, as for every field
        # instant-ngp marks a fisheye by is_fisheye alone (colmap2nerf.py writes it, with k1 and k2, for COLMAP's
        # SIMPLE_RADIAL_FISHEYE and RADIAL_FISHEYE): read as a pinhole's k1 and k2, they undistort its images wrongly
        if model not in TRANSFORMS_CAMERA_MODELS or merged.get("is_fisheye") is True:
            camera = (f"camera_model {model!r}" if model not in TRANSFORMS_CAMERA_MODELS
                      else "a fisheye camera (is_fisheye true)")
            raise WarpbagsError(f"{path}: frame {name}: {camera} is not one warpbags reads "
                                f"({', '.join(TRANSFORMS_CAMERA_MODELS)}; undistort the images first)")
        if merged.get("w") is None or merged.get("h") is None:
            width, height = image_size(image_path)
        else:
            width, height = number("w", low=0), number("h", low=0)
        if "fl_x" in merged:
            fx = number("fl_x", low=0)
            fy = number("fl_y", fx, low=0)
        elif "camera_angle_x" in merged:
            fx = 0.5 * width / math.tan(0.5 * number("camera_angle_x", low=0, high=math.pi))
            fy = 0.5 * height / math.tan(0.5 * number("camera_angle_y", low=0, high=math.pi)) \
                if "camera_angle_y" in merged else fx
        else:
            raise WarpbagsError(f"{path}: no focal length (fl_x or camera_angle_x)")
        K = np.array([[fx, 0, number("cx", width / 2)], [0, fy, number("cy", height / 2)], [0, 0, 1]], float)
        distortion = np.array([number(key, 0.0) for key in ("k1", "k2", "p1", "p2")], dtype=np.float64)
        if any(number(key, 0.0) for key in ("k3", "k4")):
            raise WarpbagsError(f"{path}: k3/k4 distortion is not supported (undistort the images first)")
        rows.append((name, image_path, np.linalg.inv(camera_to_world), K, (width, height), distortion))
    rows.sort(key=lambda row: row[0])
    repeated = [name for name, following in zip([row[0] for row in rows], [row[0] for row in rows[1:]])
                if name == following]
    if repeated:  # one image as two views: a split could hold it twice
        raise WarpbagsError(f"{', '.join(str(path) for path in sources)}: image {repeated[0]} is named by two frames")
    return LayoutCameras(
        layout="transforms",
        image_paths=[row[1] for row in rows],
        image_names=[row[0] for row in rows],
        viewmats=np.stack([row[2] for row in rows]),
        Ks=np.stack([row[3] for row in rows]),
        calibration_sizes=np.array([row[4] for row in rows], dtype=np.float64),
        distortions=np.stack([row[5] for row in rows]),
        test_names=test_names or None,
    )


def _frame_number(path: Path, name: str, fields: dict, key: str, default: object = None, low: float = -math.inf,
                  high: float = math.inf) -> float:
    """Field `key` of frame `name` in transforms file `path` (`fields`: the file's fields updated by the frame's),
    or `default` without one, as a finite float strictly between `low` and `high`.

    Raises:
        WarpbagsError: the value is not a finite number (a string of no number, null, a list, true) or lies outside
            the bounds; named with the file, the frame and the field.
    """
    value = fields.get(key)
    value = default if value is None else value  # null as absent, as w and h are
    number = math.nan
    if not isinstance(value, bool):  # JSON's true is no number, though float() takes it
        try:
            number = float(value)
        except (TypeError, ValueError):
            pass
    if not math.isfinite(number):
        raise WarpbagsError(f"{path}: frame {name}: {key} is {value!r}, not a finite number")
    if not low < number < high:
        bounds = f"above {low:g}" if high == math.inf else f"between {low:g} and {high:g}"
        raise WarpbagsError(f"{path}: frame {name}: {key} is {value!r}, not {bounds}")
    return number


def _frame_name(root: Path, frame: dict, source: Path) -> str:
    if not isinstance(frame, dict):
        raise WarpbagsError(f"{source}: a frame is {json.dumps(frame)[:40]}, not an object with a file_path")
    if not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
        raise WarpbagsError(f"{source}: a frame has no file_path (a path, got {json.dumps(frame.get('file_path'))})")
    relative = Path(str(frame["file_path"]))
    # Inside the folder as written (a linked images/ or DVC cache is the user's) or once links are resolved (a
    # scene folder reached through a link, named by its real path); else an absolute path elsewhere or one that
    # climbs out of the folder
    as_written, folder_as_written = (Path(os.path.normpath(path)) for path in (root.absolute() / relative,
                                                                                root.absolute()))
    for path, folder in ((as_written, folder_as_written), (as_written, root.resolve()),
                         ((root / relative).resolve(), root.resolve())):
        if path.is_relative_to(folder):
            name = path.relative_to(folder)
            return (name if name.suffix else _with_image_extension(root, name, frame, source)).as_posix()
    raise WarpbagsError(f"{source}: frame file_path {frame['file_path']!r} is outside the scene folder {root}; "
                        "file paths are relative to it")


def _with_image_extension(root: Path, name: Path, frame: dict, source: Path) -> Path:
    """The image `name` (a frame's file_path without extension: Blender writes "./train/r_0" for "./train/r_0.png")
    with the first of the extensions the loader reads whose file exists, full-size or downsampled (`images_2/`).

    Raises:
        WarpbagsError: no such file, named with the frame's file_path and the extensions tried.
    """
    for extension in IMAGE_EXTENSIONS:
        candidate = name.with_suffix(extension)
        if any(resolution_path(root, root / candidate, factor).is_file() for factor in FACTORS):
            return candidate
    raise WarpbagsError(f"{source}: frame file_path {frame['file_path']!r} has no extension, and no image "
                        f"{root / name}{', '.join(IMAGE_EXTENSIONS[:-1])} or {IMAGE_EXTENSIONS[-1]} exists")
