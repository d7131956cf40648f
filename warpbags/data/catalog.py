"""Resolve a scene name (a preset in `warpbags.configs.scenes`) or a folder path, and load it."""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

from warpbags.configs.scenes import SCENES, ScenePreset
from warpbags.data.loaders import load_scene
from warpbags.data.scene import Scene
from warpbags.data.synthetic import SyntheticOptions, default_cache_dir, ensure_synthetic_scene
from warpbags.errors import WarpbagsError

DEFAULT_DATA_ROOT = Path("data")


def data_root(explicit: str | Path | None = None) -> Path:
    """`explicit` (the --data-root option), else $WARPBAGS_DATA, else `data/` in the working directory."""
    if explicit is not None:
        return Path(explicit)
    return Path(os.environ.get("WARPBAGS_DATA") or DEFAULT_DATA_ROOT)


DATA_ROOT_SCENES = tuple(sorted(name for name, preset in SCENES.items() if preset.source == "data_root"))
"""The presets read from a data root (--data-root, $WARPBAGS_DATA or data/); every other scene ignores one."""


def check_data_root(scene: str | Path, explicit: str | Path | None) -> None:
    """Raise when the --data-root option given (`explicit`; None: not given) would not be read: the scene is no preset
    of `DATA_ROOT_SCENES`, or the folder does not exist. $WARPBAGS_DATA is a default for the data-root presets and is
    not checked: it may stay set in the environment while other scenes are trained.

    Raises:
        WarpbagsError: either case, naming the option.
    """
    if explicit is None:
        return
    preset = SCENES.get(str(scene))
    if preset is None or preset.source != "data_root":
        raise WarpbagsError(f"--data-root is read only by the presets {', '.join(DATA_ROOT_SCENES)}, not by scene "
                            f"{str(scene)!r}: leave it out")
    if not Path(explicit).is_dir():
        raise WarpbagsError(f"--data-root {explicit}: not a folder")


def packaged_scene_dir(name: str) -> Path:
    """Folder of a scene shipped inside the package (`warpbags/assets/<name>`)."""
    return Path(str(resources.files("warpbags") / "assets" / name))


def resolve_scene(
    scene: str | Path, root: str | Path | None = None, cache_dir: Path | None = None
) -> tuple[Path, ScenePreset | None]:
    """The folder of a named scene or a path, and its preset (None for a plain path).

    Raises:
        WarpbagsError: the scene is neither a preset nor an existing folder, or the preset's data is missing.
    """
    preset = SCENES.get(str(scene))
    if preset is None:
        folder = Path(scene)
        if folder.is_file():
            raise WarpbagsError(f"scene {scene!r}: {folder.resolve()} is a file, not a scene folder")
        if not folder.is_dir():
            raise WarpbagsError(
                f"scene {scene!r}: no folder {folder.resolve()} and no preset of that name "
                f"(presets: {', '.join(sorted(SCENES))})"
            )
        return folder, None
    if preset.source == "synthetic":
        return ensure_synthetic_scene(SyntheticOptions(**preset.synthetic), cache_dir or default_cache_dir()), preset
    base = data_root(root) if preset.source == "data_root" else packaged_scene_dir("")
    candidates = [base / folder for folder in preset.folders]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate, preset
    looked = ", ".join(str(candidate.resolve()) for candidate in candidates)
    raise WarpbagsError(f"scene {preset.name} not found (looked in {looked}): {preset.how_to_get}")


def open_scene(
    scene: str | Path,
    *,
    root: str | Path | None = None,
    resolution: int | None = None,
    normalize: bool = True,
    cache_dir: Path | None = None,
) -> Scene:
    """Load a scene by preset name (`warpbags.configs.scenes.SCENES`) or folder path.

    Args:
        scene: preset name or folder.
        root: data root for data-root presets (default $WARPBAGS_DATA or data/).
        resolution: downsampling factor; None = the preset's (or the largest available for a path).
        normalize: centre and scale to `ORBIT_RADIUS`.
        cache_dir: where generated scenes live (default $WARPBAGS_CACHE or ~/.cache/warpbags).
    """
    folder, preset = resolve_scene(scene, root, cache_dir)
    if preset is None:
        return load_scene(folder, resolution=resolution, normalize=normalize)
    return load_scene(
        folder,
        resolution=preset.resolution if resolution is None else resolution,
        name=preset.name,
        normalize=normalize,
        default_splits={key: list(value) for key, value in preset.default_splits.items()},
    )
