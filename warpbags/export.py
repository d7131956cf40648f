"""A run's results outside warpbags: its Gaussians and poses in the input scene's frame, and a turntable render.

`export_run` writes a standard 3DGS PLY, the final [C,4,4] poses and a COLMAP model of the training cameras (the
input's calibration, the corrected poses), undoing the scene normalization; `render_turntable` renders novel views on
a full orbit of the object as PNG frames and an mp4.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np
import torch

from warpbags.camera_paths import turntable_viewmats
from warpbags.data import SceneNormalization
from warpbags.data.colmap import write_model
from warpbags.data.images import image_size, resolution_path
from warpbags.data.layouts import read_layout_cameras, scaled_intrinsics
from warpbags.errors import WarpbagsError
from warpbags.files import atomic_output, writable_folder
from warpbags.gaussians import render_gaussians, sh_degree_of, to_source_frame, write_ply
from warpbags.kernels.sh import SH_C0
from warpbags.run_folder import TrainingRun, load_run, require_info
from warpbags.threads import torch_threads


@dataclass
class Calibration:
    """The training views' cameras as the input scene folder gives them, for the image files it holds.

    Attributes:
        image_folder: the folder, relative to the scene folder, that the names are relative to (COLMAP's image path):
            `images/` where the full-size images are, else the downsampled folder the run read (`images_8/`).
        image_names: C names.
        Ks: [C,3,3] float64 at `sizes`, the size of those files; sizes: [C,2] (width, height);
        distortions: [C,4] OpenCV (k1, k2, p1, p2), as the scene gives them (the images are not undistorted).
    """

    image_folder: str
    image_names: list[str]
    Ks: np.ndarray
    sizes: np.ndarray
    distortions: np.ndarray


def training_calibration(run: TrainingRun) -> Calibration:
    """The calibration of the run's training views, read again from its scene folder (a run stores its intrinsics
    only at the training resolution, after undistortion), scaled to the image files the folder holds.

    Raises:
        WarpbagsError: the scene folder is gone, or no longer holds one of the run's training views or its image.
    """
    require_info(run, "scene_root", "image_names", "resolution")
    root = Path(run.info["scene_root"])
    if not root.is_dir():
        raise WarpbagsError(f"the run's scene folder {root} is gone: the COLMAP model takes the cameras' calibration "
                            "from it (--no-colmap exports without it)")
    cameras = read_layout_cameras(root)
    index = {name: position for position, name in enumerate(cameras.image_names)}
    missing = [name for name in run.info["image_names"] if name not in index]
    if missing:
        raise WarpbagsError(f"{root} no longer holds the run's training view {missing[0]!r}: was the scene changed?")
    picked = [index[name] for name in run.info["image_names"]]
    files = []
    for position in picked:
        full = cameras.image_paths[position]
        file = full if full.is_file() else resolution_path(root, full, run.info["resolution"])
        if not file.is_file():
            raise WarpbagsError(f"image {full} is missing: was the scene changed?")
        files.append(file.relative_to(root))
    folder = PurePosixPath(os.path.commonpath([file.parent.as_posix() for file in files]) or ".")
    sizes = np.array([image_size(root / file) for file in files], dtype=np.float64)
    Ks = scaled_intrinsics(cameras.Ks[picked], cameras.calibration_sizes[picked], sizes)
    return Calibration(str(folder), [PurePosixPath(file.as_posix()).relative_to(folder).as_posix() for file in files],
                       Ks, sizes, cameras.distortions[picked])


def export_run(path: str | Path, out: str | Path | None = None, colmap: bool = True) -> tuple[Path, Path | None]:
    """Write the run's Gaussians and final poses in the input scene's own frame (not the normalized one).

    Writes `<out>/gaussians.ply` (standard 3DGS PLY), `<out>/poses_final.npy` ([C,4,4] world-to-camera, OpenCV
    axes, the training views in `config.json`'s image order) and, with `colmap`, `<out>/sparse/0/` (a COLMAP text
    model: the training views with the input's calibration, for the image files the scene folder holds, and their
    final poses, one point per Gaussian at its centre in its base colour), which COLMAP-reading trainers take as
    they are with the scene's image folder. Default `out`: `<run>/export`.

    Raises:
        WarpbagsError: the run is unfinished or unreadable; with `colmap`, its scene folder is gone or changed.
            Nothing is written then.

    Returns:
        The output folder, and with `colmap` the scene's image folder the model's image names are relative to.
    """
    run = load_run(path)
    require_info(run, "normalization")
    out = Path(out) if out is not None else run.path / "export"
    writable_folder(out, "to export into")
    calibration = training_calibration(run) if colmap else None
    normalization = SceneNormalization.from_dict(run.info["normalization"])
    out.mkdir(parents=True, exist_ok=True)
    gaussians = to_source_frame(run.params, normalization)
    write_ply(out / "gaussians.ply", gaussians)
    poses = normalization.invert_viewmats(run.poses_final.double()).numpy()
    with atomic_output(out / "poses_final.npy") as temporary:
        np.save(temporary, poses)
    if calibration is not None:
        colors = (0.5 + SH_C0 * gaussians["sh0"][:, 0, :].double()).clamp(0, 1).numpy()
        model, staging = out / "sparse" / "0", out / "sparse" / "0.partial"  # a failed write leaves no model
        shutil.rmtree(staging, ignore_errors=True)
        write_model(staging, calibration.image_names, poses, calibration.Ks, calibration.sizes[:, 0],
                    calibration.sizes[:, 1], gaussians["means"].double().numpy(), np.round(colors * 255).astype(np.uint8),
                    binary=False, distortions=calibration.distortions)
        shutil.rmtree(model, ignore_errors=True)
        staging.rename(model)
        return out, Path(run.info["scene_root"]) / calibration.image_folder
    return out, None


@torch_threads(1)
def render_turntable(path: str | Path, frames: int = 36, video: bool = True) -> Path:
    """Novel views on a full orbit of the object: `<run>/turntable/frame_XXX.png` and, with `video`,
    `<run>/turntable.mp4` (OpenCV, mp4v, 12 fps). The orbit starts at training camera 0 and turns about the
    training cameras' mean up axis through the object centre. Returns the frame folder."""
    if frames < 1:
        raise WarpbagsError(f"--frames must be >= 1, got {frames}")
    run = load_run(path)
    require_info(run, "width", "height")
    width, height = run.info["width"], run.info["height"]
    if run.intrinsics is None:
        raise WarpbagsError(f"{run.path / 'intrinsics.npy'} is missing: written by an older warpbags")
    camera_0 = run.intrinsics[0].float()
    viewmats = turntable_viewmats(run.poses_final, frames).float()
    Ks = camera_0.expand(frames, 3, 3).contiguous()
    out = run.path / "turntable"
    out.mkdir(exist_ok=True)
    for stale in out.glob("frame_*.png"):  # an earlier render of more frames must not leave its tail behind
        stale.unlink()
    backgrounds = torch.tensor(run.config.background_rgb).expand(frames, 3).contiguous()  # as trained and viewed
    with torch.no_grad():
        images, _, _ = render_gaussians(run.params, viewmats, Ks, width, height, sh_degree=sh_degree_of(run.params),
                                        backgrounds=backgrounds)
    pixels = (images.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    for index, image in enumerate(pixels):
        frame = out / f"frame_{index:03d}.png"
        if not cv2.imwrite(str(frame), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise WarpbagsError(f"could not write {frame}")
    if video:
        with atomic_output(run.path / "turntable.mp4") as temporary:
            writer = cv2.VideoWriter(str(temporary), cv2.VideoWriter_fourcc(*"mp4v"), 12, (width, height))
            if not writer.isOpened():
                raise WarpbagsError(f"OpenCV cannot write an mp4v video to {temporary}: pass --no-video for the "
                                    "frames alone")
            for image in pixels:
                writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            writer.release()
    return out
