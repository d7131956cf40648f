"""`warpbags info SCENE` and `warpbags synth OUT_DIR`: inspect a scene, write the synthetic scene."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.text import Text
from rich.table import Table

from warpbags.cli.common import clean_errors, stdout
from warpbags.cli.train_options import DATA_ROOT_HELP
from warpbags.configs.scenes import SCENES
from warpbags.data import ORBIT_RADIUS, SyntheticOptions, generate_synthetic_scene, open_scene
from warpbags.data.catalog import check_data_root
from warpbags.data.scene import Scene
from warpbags.errors import WarpbagsError
from warpbags.run_folder import RunFolder


def scene_summary(scene: Scene) -> Table:
    """A two-column rich table describing `scene`."""
    table = Table(title=f"scene {scene.name}", show_header=False, title_justify="left")
    table.add_column(style="bold cyan")
    table.add_column(overflow="fold")  # a long folder goes on to the next line, not cut short with an ellipsis
    Ks = scene.Ks
    table.add_row("folder", str(scene.root))
    table.add_row("layout", scene.layout)
    table.add_row("images", f"{scene.num_views} ({scene.image_names[0]} .. {scene.image_names[-1]})")
    table.add_row("resolution", f"{scene.width} x {scene.height}")
    same = bool((Ks - Ks[0]).abs().max() < 1e-4)
    fx, fy, cx, cy = (float(value) for value in (Ks[0, 0, 0], Ks[0, 1, 1], Ks[0, 0, 2], Ks[0, 1, 2]))
    note = "" if same else "  (view 0; views differ)"
    table.add_row("intrinsics", f"fx {fx:.2f}  fy {fy:.2f}  cx {cx:.2f}  cy {cy:.2f}{note}")
    table.add_row("masks", "yes" if scene.masks is not None else "no")
    depth_text = "no" if scene.depths is None else f"yes ({scene.depth_units} units)"
    table.add_row("depth maps", depth_text)
    points = "none" if scene.points is None else str(len(scene.points))
    table.add_row("SfM points", points)
    for key, indices in scene.splits.items():
        table.add_row(f"split {key}", Text.assemble(f"{indices}  ", (f"({scene.split_sources.get(key, '')})", "dim")))
    table.add_row("orbit radius", f"{scene.orbit_radius():.4f} (normalized; target {ORBIT_RADIUS})")
    normalization = scene.normalization
    center = ", ".join(f"{value:.4f}" for value in normalization.center)
    table.add_row("normalization", f"x' = {normalization.scale:.6f} * (x - [{center}])  (source orbit radius "
                  f"{scene.orbit_radius() / normalization.scale:.4f})")
    return table


def info(
    scene: str = typer.Argument(..., help=f"Preset name ({', '.join(sorted(SCENES))}) or a scene folder."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", help=DATA_ROOT_HELP),
    resolution: Optional[int] = typer.Option(
        None, "--resolution", "-r", help="Image downsampling factor 1, 2, 4 or 8 (default: the scene's)."
    ),
) -> None:
    """Print a scene's summary: images, resolution, intrinsics, splits, masks, depth maps, orbit radius."""
    check_data_root(scene, data_root)
    try:
        loaded = open_scene(scene, root=data_root, resolution=resolution)
    except WarpbagsError:
        trained_on = None if scene in SCENES else _run_scene_folder(Path(scene))
        if trained_on is not None:
            raise WarpbagsError(f"{scene} is a training run folder, not a scene: info takes a scene; the run's scene "
                                f"folder is {trained_on}") from None
        raise
    stdout.print(scene_summary(loaded))


def _run_scene_folder(folder: Path) -> str | None:
    """The scene folder of the training run in `folder` (its config.json's scene_root); None where `folder` holds
    no readable run config.json (a scene folder may hold a config.json of its own: its error is the one to show)."""
    if not (folder / "config.json").is_file():
        return None
    try:
        scene_root = RunFolder(folder).read_info().get("scene_root")
    except WarpbagsError:
        return None
    return scene_root if isinstance(scene_root, str) else None


def synth(
    out_dir: Path = typer.Argument(..., help="Folder to write the synthetic scene to (must not exist or be empty)."),
    views: int = typer.Option(SyntheticOptions.views, help="Number of cameras on the dome (at least 4). About one in "
                              "eight is held out for testing, never one of the 4/6/9-view splits: training on 4 views "
                              "needs 5 or more."),
    size: int = typer.Option(SyntheticOptions.width, help="Image width and height in pixels."),
    seed: int = typer.Option(SyntheticOptions.seed, help="Seed for textures and sampled points."),
    light_jitter_deg: float = typer.Option(0.0, help="Turn each view's light by up to this angle, 0-180 (lighting "
                                                     "that changes between shots)."),
    gain_jitter: float = typer.Option(0.0, help="Scale each view's colour channels by exp(N(0, this^2)), 0-1 "
                                                "(exposure and white balance changing between shots)."),
    turntable_light: bool = typer.Option(False, help="The light turns with the camera, as on a turntable capture: "
                                                     "the object's shading changes with the side it is seen from."),
    object_name: str = typer.Option("excavator", "--object",
                                    help="The object: excavator (a silhouette that differs from every side) or tankard "
                                         "(wooden, nearly symmetric, shaped and textured like maryrose)."),
) -> None:
    """Render a synthetic scene (exact poses, masks, depth maps) in the MipNeRF360 layout."""
    options = SyntheticOptions(views=views, width=size, height=size, seed=seed, light_jitter_deg=light_jitter_deg,
                               gain_jitter=gain_jitter, turntable_light=turntable_light, object=object_name)
    folder = generate_synthetic_scene(out_dir, options)
    stdout.print(f"wrote {views} views ({size}x{size}) to {folder}")


def register(app: typer.Typer) -> None:
    """Add `info` and `synth` to `app`."""
    app.command("info")(clean_errors(info))
    app.command("synth")(clean_errors(synth))
