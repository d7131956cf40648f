"""`warpbags export RUN` and `warpbags render RUN`: a run's Gaussians and poses for other tools, novel views."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from warpbags.cli.common import clean_errors, stdout
from warpbags.errors import sigterm_stops
from warpbags.run_folder import latest_run
from warpbags.export import export_run, render_turntable


def export(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the last finished under runs/)."),
    out: Optional[Path] = typer.Option(
        None, "--out", help="Output folder (default: RUN_DIR/export): a new or empty folder, or an earlier export, "
        "whose gaussians.ply, poses_final.npy and sparse/0/ are replaced; never the run folder, its scene folder or "
        "a folder that holds other files."),
    colmap: bool = typer.Option(True, "--colmap/--no-colmap",
                                help="Also write sparse/0/, a COLMAP model (text; binary where an image name holds a "
                                     "space) of the training cameras: the input's "
                                     "calibration, read again from the scene folder, with the final poses."),
) -> None:
    """Write the Gaussians (standard 3DGS PLY) and final poses in the input scene's frame: poses_final.npy holds
    [C,4,4] world-to-camera matrices with OpenCV axes, whatever the input layout, and sparse/0/ the training cameras
    as a COLMAP model that COLMAP-reading trainers (gsplat, nerfstudio; 3DGS only for undistorted input) take as it
    is."""
    folder, image_folder = export_run(run_dir or latest_run(), out, colmap=colmap)
    written = ["gaussians.ply", "poses_final.npy"] + (["sparse/0/"] if colmap else [])
    stdout.print(f"wrote {', '.join(str(folder / name) for name in written)} (input scene frame)"
                 + (f"; the model's images are in {image_folder}" if image_folder is not None else ""))


def render(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the last finished under runs/)."),
    frames: int = typer.Option(36, "--frames", help="Views on the orbit, 1 to 3600 (5 minutes of video)."),
    video: bool = typer.Option(True, "--video/--no-video",
                               help="Also write RUN_DIR/turntable.mp4 (--no-video removes an earlier one)."),
) -> None:
    """Render a turntable of novel views around the object (PNG frames, and an MP4 through OpenCV)."""
    with sigterm_stops():  # `kill` stops it as Ctrl-C does: the partial frames and video removed
        folder = render_turntable(run_dir or latest_run(), frames=frames, video=video)
    stdout.print(f"wrote {frames} frames to {folder}" + (f" and {folder.parent / 'turntable.mp4'}" if video else ""))


def register(app: typer.Typer) -> None:
    """Add `export` and `render` to `app`."""
    app.command("export")(clean_errors(export))
    app.command("render")(clean_errors(render))
