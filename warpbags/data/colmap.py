"""COLMAP sparse models through pycolmap: read cameras/poses/points, write a model (the synthetic scene, exports).

COLMAP already uses OpenCV camera axes, world-to-camera poses and pixel centres at (x+0.5, y+0.5), so its
poses and principal points are used as they are. pycolmap is imported where a model is read or written
(`_pycolmap`): it adds about 57 MiB to a process's resident memory, and scenes in other layouts (maryrose's LLFF)
never need it.
"""

from __future__ import annotations

import signal
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from warpbags.errors import WarpbagsError

if TYPE_CHECKING:
    import pycolmap


def _pycolmap():
    """pycolmap, imported on first use. Its import installs glog's failure handler for SIGTERM too, which prints a
    native stack dump when `kill` or a job scheduler stops the process; SIGTERM gets back the handler it had before
    (Python's default, or the trainer's stop with a checkpoint)."""
    previous = signal.getsignal(signal.SIGTERM)
    import pycolmap  # noqa: PLC0415

    if previous is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, previous)
    return pycolmap


SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class ColmapCamera:
    """One COLMAP camera reduced to a pinhole K plus OpenCV distortion coefficients.

    Attributes:
        width, height: the size the calibration refers to (full resolution).
        K: [3,3] float64 intrinsics at (width, height).
        distortion: [4] float64 OpenCV (k1, k2, p1, p2); all zero for pinhole models.
        model: the COLMAP model name.
    """

    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    model: str


@dataclass
class ColmapModel:
    """A sparse model with its images sorted by name.

    Attributes:
        image_names: C names, sorted.
        viewmats: [C,4,4] float64 world-to-camera.
        cameras: C `ColmapCamera`, one per image.
        points: [P,3] float64 points, colors: [P,3] uint8.
    """

    image_names: list[str]
    viewmats: np.ndarray
    cameras: list[ColmapCamera]
    points: np.ndarray
    colors: np.ndarray


def find_model_files(model_dir: Path) -> str:
    """Return "bin" or "txt" for the complete model in `model_dir`, or raise naming the missing file."""
    for extension in ("bin", "txt"):
        if (model_dir / f"cameras.{extension}").is_file() or (model_dir / f"images.{extension}").is_file():
            for stem in ("cameras", "images", "points3D"):
                if not (model_dir / f"{stem}.{extension}").is_file():
                    # a model of known poses written by hand (COLMAP's own recipe) may hold no points
                    empty = " (a model without points holds an empty points3D.txt)" if stem == "points3D" else ""
                    raise WarpbagsError(f"{model_dir / f'{stem}.{extension}'} is missing (COLMAP model "
                                        f"incomplete{empty})")
            return extension
    raise WarpbagsError(f"no COLMAP model in {model_dir}: expected cameras.bin and images.bin (or .txt)")


def _camera_from_pycolmap(camera: pycolmap.Camera, source: Path) -> ColmapCamera:
    model = camera.model.name
    params = np.asarray(camera.params, dtype=np.float64)
    distortion = np.zeros(4)
    if model == "PINHOLE":
        fx, fy, cx, cy = params
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = params
        fy = fx
    elif model == "SIMPLE_RADIAL":
        fx, cx, cy, k1 = params
        fy = fx
        distortion[0] = k1
    elif model == "RADIAL":
        fx, cx, cy, k1, k2 = params
        fy = fx
        distortion[:2] = k1, k2
    elif model == "OPENCV":
        fx, fy, cx, cy = params[:4]
        distortion[:] = params[4:8]
    else:
        raise WarpbagsError(
            f"{source}: camera {camera.camera_id} uses COLMAP model {model}, not supported "
            f"(supported: {', '.join(SUPPORTED_MODELS)}; run `colmap image_undistorter` first)"
        )
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return ColmapCamera(int(camera.width), int(camera.height), K, distortion, model)


def _read_reconstruction(model_dir: Path, extension: str) -> pycolmap.Reconstruction:
    """The pycolmap reconstruction of `model_dir/*.{extension}` ("bin" or "txt").

    Raises:
        WarpbagsError: pycolmap cannot read it, with the last line of its reason; a binary file whose entries do
            not end where it ends (`check_binary_layout`), named.
    """
    reconstruction = _pycolmap().Reconstruction()
    try:
        if extension == "bin":
            for stem in BINARY_LAYOUTS:
                if (model_dir / f"{stem}.bin").is_file():
                    check_binary_layout(model_dir / f"{stem}.bin")
            reconstruction.read_binary(str(model_dir))
        else:
            reconstruction.read_text(str(model_dir))
    except WarpbagsError:
        raise
    except Exception as error:  # ValueError/RuntimeError with a multi-line C++ message
        reason = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
        raise WarpbagsError(f"cannot read COLMAP model {model_dir}/*.{extension}: {reason}") from None
    return reconstruction


class _Entries:
    """A reader of a binary file's fields that says where the file ends too soon."""

    def __init__(self, path: Path):
        self.path, self.data, self.offset = path, path.read_bytes(), 0

    def read(self, layout: struct.Struct) -> tuple:
        return layout.unpack_from(self.data, self._advance(layout.size))

    def skip(self, count: int, size: int) -> None:
        self._advance(count * size)

    def name(self) -> None:
        """A NUL-terminated name."""
        end = self.data.find(b"\0", self.offset)
        self._advance(len(self.data) + 1 - self.offset if end < 0 else end + 1 - self.offset)

    def _advance(self, size: int) -> int:
        """Move past the next `size` bytes; returns where they start."""
        start = self.offset
        if start + size > len(self.data):
            raise WarpbagsError(f"COLMAP model file {self.path} is cut short: it ends at byte {len(self.data)}, "
                                f"within an entry that starts at byte {start} (a full disk or an interrupted copy?)")
        self.offset += size
        return start


_COUNT, _CAMERA, _IMAGE = struct.Struct("<Q"), struct.Struct("<IiQQ"), struct.Struct("<I7dI")
_POINT, _RIG, _SENSOR = struct.Struct("<Q3d3BdQ"), struct.Struct("<II"), struct.Struct("<iI")
_RIG_SENSOR, _FRAME = struct.Struct("<iIB"), struct.Struct("<II7dI")


def _walk_cameras(entries: _Entries) -> None:
    for _ in range(entries.read(_COUNT)[0]):
        camera_id, model_id = entries.read(_CAMERA)[:2]
        try:
            params = len(_pycolmap().Camera.create_from_model_id(camera_id, model_id, 1.0, 1, 1).params)
        except (TypeError, ValueError):
            raise WarpbagsError(f"COLMAP model file {entries.path}: camera {camera_id} has unknown camera model id "
                                f"{model_id}") from None
        entries.skip(params, 8)


def _walk_images(entries: _Entries) -> None:
    for _ in range(entries.read(_COUNT)[0]):
        entries.read(_IMAGE)
        entries.name()
        entries.skip(entries.read(_COUNT)[0], 24)  # x, y, point3D_id


def _walk_points3d(entries: _Entries) -> None:
    for _ in range(entries.read(_COUNT)[0]):
        entries.skip(entries.read(_POINT)[-1], 8)  # the track: image_id, point2D_idx


def _walk_rigs(entries: _Entries) -> None:
    for _ in range(entries.read(_COUNT)[0]):
        sensors = entries.read(_RIG)[1]
        if sensors > 0:
            entries.read(_SENSOR)  # the reference sensor
        for _ in range(sensors - 1):
            if entries.read(_RIG_SENSOR)[2]:
                entries.skip(7, 8)  # its pose in the rig


def _walk_frames(entries: _Entries) -> None:
    for _ in range(entries.read(_COUNT)[0]):
        entries.skip(entries.read(_FRAME)[-1], 16)  # data ids: sensor type, sensor id, data id


BINARY_LAYOUTS = {"rigs": _walk_rigs, "cameras": _walk_cameras, "frames": _walk_frames, "images": _walk_images,
                  "points3D": _walk_points3d}
"""The binary model files, each with a walk over its entries in COLMAP's layout (colmap/scene/
reconstruction_io_binary.cc)."""


def check_binary_layout(path: Path) -> None:
    """Walk the entries of the COLMAP binary file `path` (a stem of `BINARY_LAYOUTS`): each must end within the
    file, and the last where it ends. pycolmap reads on past a file's end without noticing: a file cut short took
    it 85 s to fail (a count read from beyond the end) or read back as complete, the missing bytes as garbage.

    Raises:
        WarpbagsError: the file ends within an entry, or goes on after its last; the file and the byte named.
    """
    entries = _Entries(path)
    BINARY_LAYOUTS[path.stem](entries)
    if entries.offset != len(entries.data):
        raise WarpbagsError(f"COLMAP model file {path} goes on after its last entry (byte {entries.offset} of "
                            f"{len(entries.data)}): not a COLMAP binary model file, or a damaged one")


def read_model(model_dir: Path) -> ColmapModel:
    """Read `model_dir/{cameras,images,points3D}.{bin,txt}`.

    Raises:
        WarpbagsError: a file is missing or unreadable, or a camera model is unsupported.
    """
    extension = find_model_files(model_dir)
    reconstruction = _read_reconstruction(model_dir, extension)
    registered = [image for image in reconstruction.images.values() if image.has_pose]
    if not registered:
        raise WarpbagsError(f"{model_dir / f'images.{extension}'} holds no posed images")
    registered.sort(key=lambda image: image.name)
    used = {image.camera_id for image in registered}  # a camera no posed image uses is not read (nor refused)
    cameras = {
        camera_id: _camera_from_pycolmap(camera, model_dir / f"cameras.{extension}")
        for camera_id, camera in reconstruction.cameras.items() if camera_id in used
    }
    viewmats = np.tile(np.eye(4), (len(registered), 1, 1))
    for index, image in enumerate(registered):
        viewmats[index, :3, :] = image.cam_from_world().matrix()
    points3d = list(reconstruction.points3D.values())
    points = np.array([point.xyz for point in points3d], dtype=np.float64).reshape(-1, 3)
    colors = np.array([point.color for point in points3d], dtype=np.uint8).reshape(-1, 3)
    return ColmapModel(
        image_names=[image.name for image in registered],
        viewmats=viewmats,
        cameras=[cameras[image.camera_id] for image in registered],
        points=points,
        colors=colors,
    )


def write_model(
    model_dir: Path,
    image_names: list[str],
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int | np.ndarray,
    height: int | np.ndarray,
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    binary: bool = True,
    distortions: np.ndarray | None = None,
) -> None:
    """Write a COLMAP model, one camera per image: PINHOLE, or OPENCV where the image has a distortion.

    Args:
        model_dir: output folder (created).
        image_names: C names.
        viewmats: [C,4,4] world-to-camera, OpenCV axes.
        Ks: [C,3,3] intrinsics at (width, height), pixel centres at +0.5.
        width, height: the image size the intrinsics refer to, one for all images or [C] each.
        points: [P,3] optional points; colors: [P,3] uint8.
        binary: .bin files (default) or .txt.
        distortions: [C,4] OpenCV (k1, k2, p1, p2) per image; None = none.

    Raises:
        WarpbagsError: the model does not read back as written (`_check_written`): its files are left as they are.
    """
    pycolmap = _pycolmap()

    count = len(image_names)
    widths, heights = np.broadcast_to(width, (count,)), np.broadcast_to(height, (count,))
    distortions = np.zeros((count, 4)) if distortions is None else np.asarray(distortions, dtype=np.float64)
    reconstruction = pycolmap.Reconstruction()
    for index, (name, viewmat, K, distortion) in enumerate(
            zip(image_names, np.asarray(viewmats), np.asarray(Ks), distortions), start=1):
        params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        distorted = bool(np.any(distortion != 0))
        camera = pycolmap.Camera(
            model="OPENCV" if distorted else "PINHOLE",
            width=int(widths[index - 1]),
            height=int(heights[index - 1]),
            params=params + list(distortion) if distorted else params,
            camera_id=index,
        )
        reconstruction.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=name, camera_id=index, image_id=index)
        pose = pycolmap.Rigid3d(np.asarray(viewmat[:3, :4], dtype=np.float64))
        reconstruction.add_image_with_trivial_frame(image, pose)
    if points is not None:
        colors = np.zeros_like(points, dtype=np.uint8) if colors is None else colors
        for xyz, color in zip(np.asarray(points, dtype=np.float64), np.asarray(colors, dtype=np.uint8)):
            reconstruction.add_point3D(xyz, pycolmap.Track(), color)
    model_dir.mkdir(parents=True, exist_ok=True)
    if binary:
        reconstruction.write_binary(str(model_dir))
    else:
        reconstruction.write_text(str(model_dir))
    _check_written(model_dir, "bin" if binary else "txt", reconstruction)


def _check_written(model_dir: Path, extension: str, written: pycolmap.Reconstruction) -> None:
    """Read the model just written to `model_dir` back: pycolmap's writers ignore I/O errors, so a full disk or a
    file-size limit leaves files cut short that they report as written. A text file cut within a line fails to read;
    one cut at a line's end reads as fewer cameras, images or points.

    Raises:
        WarpbagsError: the model cannot be read back, or holds other counts than `written`; the folder named.
    """
    try:
        again = _read_reconstruction(model_dir, extension)
    except WarpbagsError as error:
        raise WarpbagsError(f"the COLMAP model written to {model_dir} is damaged (a full disk or a file-size "
                            f"limit?): {error}") from None
    read_back, expected = ((model.num_cameras(), model.num_images(), model.num_points3D())
                           for model in (again, written))
    if read_back != expected:
        raise WarpbagsError(f"the COLMAP model written to {model_dir} is incomplete (a full disk or a file-size "
                            "limit?): it reads back as {} cameras, {} images and {} points of {}, {} and {}".format(
                                *read_back, *expected))
