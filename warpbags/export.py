"""A run's results outside warpbags: its Gaussians and poses in the input scene's frame, and a turntable render.

`export_run` writes a standard 3DGS PLY, the final [C,4,4] poses and a COLMAP model of the training cameras (the
input's calibration, the corrected poses), undoing the scene normalization; `render_turntable` renders novel views on
a full orbit of the object as PNG frames and an mp4.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np
import torch

from warpbags.camera_paths import turntable_viewmats
from warpbags.data.colmap import write_model
from warpbags.data.scene import SceneNormalization
from warpbags.data.images import image_size, resolution_path
from warpbags.data.layouts import read_layout_cameras, scaled_intrinsics
from warpbags.errors import WarpbagsError
from warpbags.files import (atomic_output, missing_folders, temporary_name, writable_file, writable_folder,
                            write_image)
from warpbags.gaussians import opacity_weighted_center, render_gaussians, sh_degree_of, to_source_frame, write_ply
from warpbags.kernels.sh import SH_C0
from warpbags.run_folder import TrainingRun, load_run, require_info, run_normalization
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


# What an export writes into its folder: a folder holding only these (sparse/ only 0/ and the 0.partial/ of a write
# cut short, each of text files) is an earlier export, which an export may replace; any other non-empty folder
# is refused. The atomic writes' temporaries are named too, so that one left by a killed export does not block.
EXPORT_FILES = tuple(name for written in ("gaussians.ply", "poses_final.npy")
                     for name in (written, temporary_name(written)))
EXPORT_MODEL_FOLDERS = ("0", "0.partial")


def check_export_folder(out: Path, run: TrainingRun) -> None:
    """Check, before anything is written, that `out` may receive an export of `run`: a new or empty folder, or an
    earlier export (gaussians.ply, and nothing but `EXPORT_FILES` and a sparse/ of COLMAP models), and neither the run
    folder nor its scene folder, nor a folder that holds either, nor a folder inside another run's.

    Raises:
        WarpbagsError: it may not, or `out` is a file or cannot be written; the offending path named.
    """
    writable_folder(out, "to export into")
    resolved = out.resolve()
    protected = [("the run folder", run.path)]
    if run.info.get("scene_root"):
        protected.append(("the run's scene folder", Path(run.info["scene_root"])))
    for what, folder in protected:
        folder = folder.resolve()
        if resolved == folder or resolved in folder.parents:
            where = what if resolved == folder else f"a folder that holds {what} {folder}"
            raise WarpbagsError(f"--out {out} is {where}: an export would replace its files; choose a new folder")
    own = run.path.resolve()
    for folder in (resolved, *resolved.parents):  # another run's export/ would take this run's model in silence
        if folder == own:
            break
        if (folder / "config.json").is_file():
            raise WarpbagsError(f"--out {out} is inside the run folder {folder}, another run than {run.path}: export "
                                "into this run's folder or one of no run")
    if not out.is_dir():
        return
    entries = sorted(out.iterdir())
    refusal = "export into a new or empty folder, or one that an earlier export wrote"
    for entry in entries:
        if entry.is_symlink():
            raise WarpbagsError(f"{entry} is a link, which an export does not write: {refusal}")
        if entry.name in EXPORT_FILES and not entry.is_file():
            raise WarpbagsError(f"{entry} is a folder, where an export writes a file: {refusal}")
        if entry.name == "sparse" and not entry.is_dir():
            raise WarpbagsError(f"{entry} is a file, where an export writes a folder (sparse/0/): {refusal}")
        if entry.name == "sparse" and not _export_models(entry):
            raise WarpbagsError(f"{entry} holds more than the COLMAP model sparse/0/ an export writes: {refusal}")
    foreign = [entry.name for entry in entries if entry.name not in (*EXPORT_FILES, "sparse")]
    if foreign:
        shown = ", ".join(foreign[:4]) + (f" and {len(foreign) - 4} more" if len(foreign) > 4 else "")
        raise WarpbagsError(f"--out {out} is not empty and not an earlier export (it holds {shown}): {refusal}")
    if entries and not (out / "gaussians.ply").is_file():
        raise WarpbagsError(f"--out {out} is not empty and not an earlier export (no gaussians.ply): {refusal}")


def _export_models(sparse: Path) -> bool:
    """Whether `sparse` holds only what an export writes there: 0/ (and a 0.partial/ left by a failed write), each
    a COLMAP model (plain *.txt or *.bin files)."""
    for model in sparse.iterdir():
        if model.name not in EXPORT_MODEL_FOLDERS or model.is_symlink() or not model.is_dir():
            return False
        if not all(file.is_file() and not file.is_symlink() and file.suffix in (".txt", ".bin")
                   for file in model.iterdir()):
            return False
    return True


def export_run(path: str | Path, out: str | Path | None = None, colmap: bool = True) -> tuple[Path, Path | None]:
    """Write the run's Gaussians and final poses in the input scene's own frame (not the normalized one).

    Writes `<out>/gaussians.ply` (standard 3DGS PLY), `<out>/poses_final.npy` ([C,4,4] world-to-camera, OpenCV
    axes, the training views in `config.json`'s image order) and, with `colmap`, `<out>/sparse/0/` (a COLMAP text
    model, binary where an image name holds a space, at which the text format would split it: the training views
    with the input's calibration, for the image files the scene folder holds, and their final poses, one point per
    Gaussian at its centre in its base colour), which COLMAP-reading trainers take as
    they are with the scene's image folder. Default `out`: `<run>/export`. `out` must be a new or empty folder or
    an earlier export (`check_export_folder`), never the run folder or its scene folder: an export replaces the
    files of an earlier one and nothing else.

    Raises:
        WarpbagsError: the run is unfinished or unreadable; `out` may not receive the export; with `colmap`, its
            scene folder is gone or changed. Nothing is written then. With `colmap`, the model does not read back
            as written (a full disk): an earlier export is left as it was.

    Returns:
        The output folder, and with `colmap` the scene's image folder the model's image names are relative to.
    """
    run = load_run(path)
    normalization = run_normalization(run)
    out = Path(out) if out is not None else run.path / "export"
    check_export_folder(out, run)
    calibration = training_calibration(run) if colmap else None
    made = missing_folders(out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _write_export(run, out, normalization, calibration)
    except BaseException:
        if made:  # a folder this export made holds nothing else: a failed write (a full disk) leaves none of it
            shutil.rmtree(made[-1], ignore_errors=True)
        raise


def _write_export(run: TrainingRun, out: Path, normalization: SceneNormalization,
                  calibration: Calibration | None) -> tuple[Path, Path | None]:
    """`export_run`'s files into the existing folder `out`. The COLMAP model is staged in sparse/0.partial/ and
    read back (`write_model`) before anything else is written, and replaces sparse/0/ last: a write that fails (a
    full disk) leaves an earlier export's model, and with a failed model its other files too."""
    gaussians = to_source_frame(run.params, normalization)
    poses = normalization.invert_viewmats(run.poses_final.double()).numpy()
    model, staging = out / "sparse" / "0", out / "sparse" / "0.partial"
    made = missing_folders(staging)
    try:
        if calibration is not None:
            shutil.rmtree(staging, ignore_errors=True)  # one that a killed export left
            colors = (0.5 + SH_C0 * gaussians["sh0"][:, 0, :].double()).clamp(0, 1).numpy()
            write_model(staging, calibration.image_names, poses, calibration.Ks, calibration.sizes[:, 0],
                        calibration.sizes[:, 1], gaussians["means"].double().numpy(),
                        np.round(colors * 255).astype(np.uint8),
                        binary=any(" " in name or "\t" in name for name in calibration.image_names),
                        distortions=calibration.distortions)
        write_ply(out / "gaussians.ply", gaussians)
        with atomic_output(out / "poses_final.npy") as temporary:
            np.save(temporary, poses)
    except BaseException:
        shutil.rmtree(made[-1] if made else staging, ignore_errors=True)  # sparse/ too where this export made it
        raise
    if calibration is None:  # an earlier export's model, which these poses no longer match, is removed
        shutil.rmtree(out / "sparse", ignore_errors=True)
        return out, None
    shutil.rmtree(model, ignore_errors=True)
    staging.rename(model)
    return out, Path(run.info["scene_root"]) / calibration.image_folder


MAX_TURNTABLE_FRAMES = 3600  # 5 minutes of the video's 12 fps
TURNTABLE_BATCH = 8  # frames rendered at once: a render's memory is that of 8 frames whatever --frames is
TURNTABLE_STAGING = ".partial"  # in turntable/, where the frames wait until all are written


def _video_writer(path: Path, width: int, height: int) -> cv2.VideoWriter:
    """OpenCV's mp4v writer at 12 fps for frames of width x height (an odd side repeats its last row or column)."""
    # read when OpenCV first starts FFmpeg: FFmpeg's own lines ("moov atom not found" of a video `_check_video` finds
    # cut short) would come before the one line that reports the failure
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 12, (width + width % 2, height + height % 2))
    if not writer.isOpened():
        raise WarpbagsError(f"OpenCV cannot write an mp4v video to {path}: pass --no-video for the frames alone")
    return writer


def _check_video(path: Path, frames: int, target: Path) -> None:
    """Open the video just written to `path` (to replace `target`) and count its frames: OpenCV's writer reports no
    write error, so a full disk or a file-size limit leaves a video cut short that no player opens.

    Raises:
        WarpbagsError: it does not open, or holds other than `frames` frames; `target` named.
    """
    capture = cv2.VideoCapture(str(path))
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else None
    finally:
        capture.release()
    if count != frames:
        found = "does not open as a video" if count is None else f"holds {count} of its {frames} frames"
        raise WarpbagsError(f"could not write the turntable video {target}: the video written {found} (a full disk "
                            "or a file-size limit?); an earlier render is kept as it was")


def turntable_frame_name(index: int) -> str:
    """The file name of turntable frame `index`: 4 digits, so that the names of up to `MAX_TURNTABLE_FRAMES` frames
    sort in frame order (frame_0999.png before frame_1000.png)."""
    return f"frame_{index:04d}.png"


@torch_threads(1)
def render_turntable(path: str | Path, frames: int = 36, video: bool = True) -> Path:
    """Novel views on a full orbit of the object: `<run>/turntable/frame_XXXX.png` and, with `video`,
    `<run>/turntable.mp4` (OpenCV, mp4v, 12 fps; without it, an earlier render's video is removed). The orbit
    starts at training camera 0 and turns about the training cameras' common up axis through the Gaussians'
    opacity-weighted centre, where `warpbags view` first looks (a model trained from noisy poses lies off the origin).

    The frames are rendered `TURNTABLE_BATCH` at a time into a staging folder and replace an earlier render's only
    when all are written (the video likewise, once it opens as a video of all frames): a render stopped or failed
    (a full disk) leaves the earlier one as it was. Other files in turntable/ are kept. Returns the frame folder.
    """
    if not 1 <= frames <= MAX_TURNTABLE_FRAMES:
        raise WarpbagsError(f"--frames must be in [1, {MAX_TURNTABLE_FRAMES}] ({MAX_TURNTABLE_FRAMES // 12 // 60} "
                            f"minutes of video at 12 fps), got {frames}")
    run = load_run(path)
    require_info(run, "width", "height")
    width, height = run.info["width"], run.info["height"]
    if run.intrinsics is None:
        raise WarpbagsError(f"{run.path / 'intrinsics.npy'} is missing: written by an older warpbags")
    out = writable_folder(run.path / "turntable", "for the turntable frames")
    names = [turntable_frame_name(index) for index in range(frames)]
    # written, or removed as stale (an earlier render's, 3 digits where an earlier warpbags named it)
    for name in names + [path.name for path in out.glob("frame_*.png")]:
        writable_file(out / name, "to write a turntable frame to")
    video_path = run.path / "turntable.mp4"
    if video or video_path.exists():  # written, or removed as stale (an earlier render's shows other frames)
        writable_file(video_path, "to write the turntable video to")
    viewmats = turntable_viewmats(run.poses_final, frames, opacity_weighted_center(run.params)).float()
    Ks = run.intrinsics[0].float().expand(frames, 3, 3).contiguous()
    backgrounds = torch.tensor(run.config.background_rgb).expand(frames, 3).contiguous()  # as trained and viewed
    out.mkdir(exist_ok=True)
    staging = out / TURNTABLE_STAGING
    shutil.rmtree(staging, ignore_errors=True)  # a render killed before it could remove its own
    staging.mkdir()
    try:
        with contextlib.ExitStack() as stack:
            writer = None
            if video:  # written beside, it replaces an earlier render's video when every frame is in it
                written_video = stack.enter_context(atomic_output(video_path))
                writer = _video_writer(written_video, width, height)
                stack.callback(writer.release)
            for start in range(0, frames, TURNTABLE_BATCH):
                batch = slice(start, min(start + TURNTABLE_BATCH, frames))
                with torch.no_grad():
                    images, _, _ = render_gaussians(run.params, viewmats[batch], Ks[batch], width, height,
                                                    sh_degree=sh_degree_of(run.params), backgrounds=backgrounds[batch])
                pixels = (images.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
                for name, image in zip(names[batch], pixels):
                    frame = staging / name
                    try:
                        write_image(frame, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
                    except OSError as error:
                        raise WarpbagsError(f"could not write the turntable frame {out / name}: "
                                            f"{error.strerror or error}; an earlier render is kept as it was") from None
                    if writer is not None:
                        # mp4v holds even sizes only (OpenCV would drop an odd size's last row or column)
                        padded = np.pad(image, ((0, height % 2), (0, width % 2), (0, 0)), mode="edge")
                        writer.write(cv2.cvtColor(padded, cv2.COLOR_RGB2BGR))
            if writer is not None:  # finished, and checked before it replaces the earlier video
                writer.release()
                _check_video(written_video, frames, video_path)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if not video:
        video_path.unlink(missing_ok=True)
    # an earlier render of more frames must not leave its tail behind, nor one of 3-digit names (an earlier
    # warpbags's) its frames beside these
    for stale in out.glob("frame_*.png"):
        stale.unlink()
    for name in names:
        os.replace(staging / name, out / name)
    staging.rmdir()
    return out
