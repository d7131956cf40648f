"""A run's results outside warpbags: its Gaussians and poses in the input scene's frame, and a turntable render.

`export_run` writes a standard 3DGS PLY and the final [C,4,4] poses, undoing the scene normalization;
`render_turntable` renders novel views on a full orbit of the object as PNG frames and an mp4.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from warpbags.camera_paths import turntable_viewmats
from warpbags.data import SceneNormalization
from warpbags.errors import WarpbagsError
from warpbags.evaluation import load_run
from warpbags.files import atomic_output
from warpbags.gaussians import render_gaussians, sh_degree_of, to_source_frame, write_ply
from warpbags.threads import torch_threads


def export_run(path: str | Path, out: str | Path | None = None) -> Path:
    """Write the run's Gaussians and final poses in the input scene's own frame (not the normalized one).

    Writes `<out>/gaussians.ply` (standard 3DGS PLY) and `<out>/poses_final.npy` ([C,4,4] world-to-camera,
    OpenCV axes, the training views in `config.json`'s image order). Default `out`: `<run>/export`.
    """
    run = load_run(path)
    if "normalization" not in run.info:
        raise WarpbagsError(f"{run.path / 'config.json'} has no normalization: written by an older warpbags")
    normalization = SceneNormalization(tuple(run.info["normalization"]["center"]), run.info["normalization"]["scale"])
    out = Path(out) if out is not None else run.path / "export"
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "gaussians.ply", to_source_frame(run.params, normalization.center, normalization.scale))
    poses = normalization.invert_viewmats(run.poses_final)
    with atomic_output(out / "poses_final.npy") as temporary:
        np.save(temporary, poses.numpy())
    return out


@torch_threads(1)
def render_turntable(path: str | Path, frames: int = 36, video: bool = True) -> Path:
    """Novel views on a full orbit of the object: `<run>/turntable/frame_XXX.png` and, with `video`,
    `<run>/turntable.mp4` (OpenCV, mp4v, 12 fps). The orbit starts at training camera 0 and turns about the
    training cameras' mean up axis through the object centre. Returns the frame folder."""
    if frames < 1:
        raise WarpbagsError(f"--frames must be >= 1, got {frames}")
    run = load_run(path)
    width, height = run.info["width"], run.info["height"]
    if not (run.path / "intrinsics.npy").is_file():
        raise WarpbagsError(f"{run.path / 'intrinsics.npy'} is missing: written by an older warpbags")
    camera_0 = torch.from_numpy(np.load(run.path / "intrinsics.npy"))[0].float()
    viewmats = turntable_viewmats(run.poses_final, frames).float()
    Ks = camera_0.expand(frames, 3, 3).contiguous()
    out = run.path / "turntable"
    out.mkdir(exist_ok=True)
    for stale in out.glob("frame_*.png"):  # an earlier render of more frames must not leave its tail behind
        stale.unlink()
    with torch.no_grad():
        images, _, _ = render_gaussians(run.params, viewmats, Ks, width, height, sh_degree=sh_degree_of(run.params),
                                        backgrounds=torch.ones(frames, 3))
    pixels = (images.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    for index, image in enumerate(pixels):
        frame = out / f"frame_{index:03d}.png"
        if not cv2.imwrite(str(frame), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise WarpbagsError(f"could not write {frame}")
    if video:
        with atomic_output(run.path / "turntable.mp4") as temporary:
            writer = cv2.VideoWriter(str(temporary), cv2.VideoWriter_fourcc(*"mp4v"), 12, (width, height))
            for image in pixels:
                writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            writer.release()
    return out
