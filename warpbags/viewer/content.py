"""What `warpbags view` shows: the Gaussians and, for a run folder, its training cameras and their pose history.

Every pose here lives in the model's frame (the frame of the optimized cameras, where the Gaussians were fitted).
The reference poses are mapped into it by the sim(3) that `warpbags eval` uses (`alignment_for`): Umeyama on the
camera centres or, where Procrustes cannot be fitted to the reference cameras (fewer than 3, or centres on one line),
SPARF's pairwise alignment; fitted from the optimized cameras to the reference ones, and inverted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from warpbags.alignment import align_viewmats, alignment_for, pose_errors
from warpbags.camera_paths import mean_up_axis
from warpbags.configs.train import BACKGROUNDS
from warpbags.errors import WarpbagsError
from warpbags.gaussians import opacity_weighted_center, read_ply, sh_degree_of
from warpbags.pose_history import HISTORY_FILE, read_pose_history
from warpbags.run_folder import RunFolder

THUMBNAIL_SIDE = 160  # px: the longer side of the pictures shown on the frustums (they travel to every browser)


@dataclass
class TrainingCameras:
    """A run's C training cameras, all [C,4,4] world-to-camera (OpenCV axes) in the model's frame.

    Attributes:
        Ks: [C,3,3] intrinsics at (width, height).
        width, height: the training image size.
        start: the poses the optimization started from (poses_start.npy: the given poses, poses_init.npy, after
            the mask-centroid start and the silhouette-coherence solve where the run used them), or None.
        reference: the reference (dataset) poses aligned to the model's frame, or None.
        iterations: [T] the iterations of the pose frames, increasing (the last is the final poses).
        frames: [T,C,4,4] the optimized poses at those iterations.
        images: [C,h,w,3] uint8 thumbnails of the training images, or None when the scene is gone.
    """

    Ks: np.ndarray
    width: int
    height: int
    start: np.ndarray | None
    reference: np.ndarray | None
    iterations: np.ndarray
    frames: np.ndarray
    images: np.ndarray | None = None

    @property
    def final(self) -> np.ndarray:
        return self.frames[-1]


@dataclass
class ViewerContent:
    """The model to render and what to draw around it.

    Attributes:
        name: shown in the GUI (run folder or file name).
        params: raw 3DGS parameters (`warpbags.gaussians`), on the CPU.
        background: RGB in [0, 1] behind the Gaussians (the run's training background; white for a bare PLY).
        cameras: the training cameras, or None for a bare PLY.
    """

    name: str
    params: dict[str, torch.Tensor]
    background: tuple[float, float, float] = BACKGROUNDS["white"]
    cameras: TrainingCameras | None = None
    sh_degree: int = field(init=False)

    def __post_init__(self) -> None:
        self.sh_degree = sh_degree_of(self.params)

    def center(self) -> np.ndarray:
        """[3] opacity-weighted mean of the Gaussian centres: where the viewer's camera looks first."""
        return opacity_weighted_center(self.params).double().numpy()

    def up(self) -> np.ndarray | None:
        """[3] the training cameras' mean up direction, or None without cameras."""
        if self.cameras is None:
            return None
        return mean_up_axis(torch.from_numpy(self.cameras.final).double()).numpy()


def load_viewer_content(path: str | Path, log: Callable[[str], None] = print) -> ViewerContent:
    """Read a run folder (Gaussians, cameras, pose history) or a bare 3DGS PLY file from any tool.

    Raises:
        WarpbagsError: the path is missing, a folder without gaussians.ply, or not a 3DGS PLY; named in one line.
    """
    path = Path(path)
    if not path.exists():
        raise WarpbagsError(f"{path}: no such run folder or PLY file")
    if path.is_file():
        return ViewerContent(path.name, read_ply(path))
    ply = path / "gaussians.ply"
    if not ply.is_file():
        raise WarpbagsError(f"{ply} is missing: not a finished run (pass a run folder or a .ply file)")
    params = read_ply(ply)
    info = _read_run_info(path)
    if info is None:
        return ViewerContent(path.name, params)
    background = RunFolder(path).saved_config(info).background_rgb  # a config.json of no run is named
    return ViewerContent(path.name, params, background, _training_cameras(path, info, log))


def _read_run_info(path: Path) -> dict | None:
    """config.json of a run, or None for a folder that merely holds a PLY (an export)."""
    if not (path / "config.json").is_file():
        return None
    return RunFolder(path).read_info()


def _training_cameras(path: Path, info: dict, log: Callable[[str], None]) -> TrainingCameras | None:
    """The run's cameras, or None (logged) when it lacks the files to draw them."""
    arrays = RunFolder(path).read_cameras()  # every camera file checked as eval and agree check them
    Ks, final, start = arrays["intrinsics"], arrays["poses_final"], arrays["poses_start"]
    if Ks is None or final is None or "width" not in info:
        log(f"{path}: no intrinsics.npy, poses_final.npy or image size: showing the Gaussians without cameras")
        return None
    iterations, frames = _pose_frames(path, info, start, final)
    reference = _aligned_reference(final, arrays["poses_true"], log)
    return TrainingCameras(Ks, info["width"], info["height"], start, reference, iterations, frames,
                           _thumbnails(info, log))


def _pose_frames(path: Path, info: dict, start: np.ndarray | None, final: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Iterations [T] and poses [T,C,4,4]: the start at 0, the recorded history, the final poses at the end (after
    the run's coarse and repair iterations; in a run's coarse/, after its coarse iterations)."""
    config = RunFolder(path).saved_config(info)
    # coarse/, the coarse stage's result written inside a run folder when a repair stage follows, holds the run's
    # config: its poses are those after the coarse iterations
    coarse = path.name == "coarse" and (path.parent / "config.json").is_file()
    last = config.iters if coarse else config.total_iters
    iterations, frames = [], []
    if start is not None:
        iterations, frames = [0], [start]
    history = read_pose_history(path)
    if history is not None and history.viewmats.shape[1] != len(final):
        raise WarpbagsError(f"{path / HISTORY_FILE} holds {history.viewmats.shape[1]} cameras, the run's poses "
                            f"{len(final)} (poses_final.npy)")
    if history is not None:
        recorded = (history.iterations > 0) & (history.iterations < last)
        iterations += history.iterations[recorded].tolist()
        frames += list(history.viewmats[recorded].astype(np.float64))
    return np.array(iterations + [last]), np.stack(frames + [final])


def _aligned_reference(final: np.ndarray, true: np.ndarray | None, log: Callable[[str], None]) -> np.ndarray | None:
    """`true` (poses_true.npy) mapped into the model's frame, as `warpbags eval` maps the test cameras; None
    without it."""
    if true is None:
        return None
    final_t, true_t = torch.from_numpy(final), torch.from_numpy(true)
    try:
        sim3 = pose_errors(final_t, true_t, alignment=alignment_for(true_t))["sim3"]
    except ValueError as error:
        log(f"reference cameras left out: {error}")
        return None
    return align_viewmats(true_t, sim3.inverse()).numpy()


def _thumbnails(info: dict, log: Callable[[str], None]) -> np.ndarray | None:
    """[C,h,w,3] uint8 training images from the run's scene folder, in training order; None when unreadable."""
    from warpbags.data import load_scene  # noqa: PLC0415 - only runs with a scene folder need the loaders

    try:
        scene = load_scene(info["scene_root"], resolution=info.get("resolution"), name=info.get("scene"),
                           load_depths=False)
        order = [scene.image_names.index(name) for name in info["image_names"]]
    except (WarpbagsError, KeyError, ValueError, OSError) as error:
        log(f"training images unavailable ({error}): frustums without pictures")
        return None
    images = scene.images[order].numpy()
    factor = THUMBNAIL_SIDE / max(images.shape[1:3])
    size = (max(1, round(images.shape[2] * factor)), max(1, round(images.shape[1] * factor)))
    return np.stack([(cv2.resize(image, size, interpolation=cv2.INTER_AREA) * 255 + 0.5).clip(0, 255)
                     for image in images]).astype(np.uint8)
