"""What the benchmarks share: their small synthetic scenes, the scene loader, the `--depth` maps, the `--preset` /
`--set` / `--json` options, comma-separated number lists, and the settings merge.

The scripts run as `python bench/NAME.py`, so this folder is on `sys.path` and they import it as `common`. Bad
input raises `WarpbagsError` (one line); each script wraps its `main` in `clean_errors`, which prints it as
`error: ...` and exits with code 2, as the CLI does.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any, Iterable

from warpbags.devices import init_warp_quietly

init_warp_quietly()  # the tables, not Warp's banner and module loads, as the CLI

from warpbags.configs.scenes import TELEPHOTO_OPTICS  # noqa: E402
from warpbags.configs.train import DEFAULT_PRESET, MAX_HULL_RESOLUTION, load_preset, parse_settings  # noqa: E402
from warpbags.data import ORBIT_RADIUS, SyntheticOptions, ensure_synthetic_scene, load_scene, open_scene  # noqa: E402
from warpbags.data.noise import monocular_like_depths  # noqa: E402
from warpbags.errors import WarpbagsError  # noqa: E402
from warpbags.files import atomic_output, finite_json, writable_file  # noqa: E402
from warpbags.trainer import Trainer, training_scene  # noqa: E402

SMALL_SCENES = {
    # the synthetic scene, small enough for many runs
    "synthetic-small": SyntheticOptions(views=16, width=96, height=96),
    # the same object with maryrose's optics and framing (configs/scenes.py: synthetic-tele)
    "synthetic-tele-small": SyntheticOptions(views=16, width=128, height=128, **TELEPHOTO_OPTICS),
    # the same cameras at 256 px, for schedules whose last rounds train above the quick preset's 128 px
    "synthetic-tele-256": SyntheticOptions(views=16, width=256, height=256, **TELEPHOTO_OPTICS),
    # synthetic-tele-small with the light turned by up to 30 deg and the colour channels scaled by ~10% per view,
    # as on a capture whose object was moved between sequences (maryrose): the images disagree beyond the poses
    "synthetic-tele-lit": SyntheticOptions(views=16, width=128, height=128, **TELEPHOTO_OPTICS,
                                           light_jitter_deg=30.0, gain_jitter=0.1),
    # synthetic-tele-small lit as on a turntable (maryrose): the light turns with the camera, so each part of the
    # object is shaded differently from each side it is seen from
    "synthetic-tele-turntable": SyntheticOptions(views=16, width=128, height=128, **TELEPHOTO_OPTICS,
                                                 turntable_light=True),
    # maryrose's optics and framing with a tankard like hers lying on its side instead of the excavator: a nearly
    # symmetric silhouette and a low-contrast, repetitive grain
    "synthetic-tele-tankard": SyntheticOptions(views=16, width=128, height=128, **TELEPHOTO_OPTICS,
                                               object="tankard"),
}


def open_bench_scene(name: str):
    """A scene by name: one of `SMALL_SCENES` (generated once and cached), else a preset or a scene folder
    (`warpbags.data.open_scene`, which raises `WarpbagsError` for an unknown one)."""
    if name in SMALL_SCENES:
        return load_scene(ensure_synthetic_scene(SMALL_SCENES[name]), name=name)
    return open_scene(name)


def with_depth(scene, depth: str):
    """The scene with the depth maps of `--depth`: its own ("true"), degraded ("monocular", seed 0) or none."""
    if depth == "true":
        return scene
    if depth == "none":
        return dataclasses.replace(scene, depths=None)
    if scene.depths is None:
        raise WarpbagsError(f"--depth monocular: scene {scene.name} has no depth maps to degrade")
    return dataclasses.replace(scene, depths=monocular_like_depths(scene.depths, seed=0))


def merge_settings(base: dict, extra: dict) -> dict:
    """`base` with `extra`'s settings on top; a group given as a dict (`camera`, `repair`, ...) is merged field by
    field, `extra`'s fields winning."""
    merged = dict(base)
    for key, value in extra.items():
        merged[key] = {**merged.get(key, {}), **value} if isinstance(value, dict) else value
    return merged


def check_options(checks: Iterable[tuple[bool, str]]) -> None:
    """Raise the message of the first failed `(ok, message)` check: a script's option values checked before any
    work, each message naming its option and value.

    Raises:
        WarpbagsError: a check that failed.
    """
    for ok, message in checks:
        if not ok:
            raise WarpbagsError(message)


def pose_noise_checks(rot: float, trans: float) -> list[tuple[bool, str]]:
    """`check_options` checks of a `--rot` (std, degrees) and a `--trans` (std per axis) value, by these options'
    names: the TrainConfig check they would reach later names `warpbags train`'s --rot-noise-deg and --trans-noise,
    which the benchmarks lack, and comes only once a run starts. A NaN fails both comparisons."""
    return [(0 <= rot <= 180, f"--rot must be in [0, 180] (a std in degrees), got {rot:g}"),
            (0 <= trans <= ORBIT_RADIUS, f"--trans must be in [0, {ORBIT_RADIUS:g}] (a std in scene units, the "
                                         f"cameras orbiting at radius {ORBIT_RADIUS:g}), got {trans:g}")]


def resolution_check(resolution: int) -> tuple[bool, str]:
    """The `check_options` check of a visual hull's `--resolution` (voxels per axis of its fine pass), in the range
    training allows its `hull_resolution`: 0 or less fails deep in the carve (a division by zero), and above the
    maximum the first pass's (1.5 x resolution)^3 voxels take gigabytes."""
    return (2 <= resolution <= MAX_HULL_RESOLUTION,
            f"--resolution must be in [2, {MAX_HULL_RESOLUTION}] (voxels per axis), got {resolution}")


def procrustes_views_check(given: str, fewest: int) -> tuple[bool, str]:
    """The `check_options` check of a script whose pose errors are after sim(3) Procrustes alignment of the camera
    centres, which needs 3 of them: `given`, the `--views` option as the message shows it, and `fewest`, the least
    view count it asks for (named too where the option is a list of counts)."""
    got = "" if given == str(fewest) else f", got {fewest}"
    return fewest >= 3, f"--views {given}: sim(3) Procrustes alignment needs 3 cameras or more{got}"


def check_json(path: Path | None) -> None:
    """Check a `--json` file writable before any work: the scripts write it after their first row, which may come
    after hours of training, and a folder at that path (or a file where its folder should be) would fail only then.

    Raises:
        WarpbagsError: `path` cannot be written (`warpbags.files.writable_file`).
    """
    if path is not None:
        writable_file(path, "for --json")


def check_view_counts(scenes: dict, view_counts: Iterable[int]) -> None:
    """Check that every loaded scene has each view count's training views, before the first run: a count a scene
    lacks fails otherwise when its run starts, after the runs of the counts before it.

    Raises:
        WarpbagsError: a scene with too few images for a count (`Scene.train_views`, which names both).
    """
    for scene in scenes.values():
        for count in view_counts:
            scene.train_views(count)


def add_training_options(parser: argparse.ArgumentParser, set_help: str, json_help: str | None = None) -> None:
    """Add `--preset`, `--set NAME=VALUE` (dest "settings", repeatable) and, with `json_help`, `--json PATH`."""
    parser.add_argument("--preset", default=DEFAULT_PRESET, help=f"the TrainConfig preset (default: {DEFAULT_PRESET})")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="NAME=VALUE", help=set_help)
    if json_help is not None:
        parser.add_argument("--json", type=Path, help=json_help)


def training_overrides(args: argparse.Namespace, fixed: dict[str, str] | None = None,
                       runs: Iterable[tuple[str, dict]] = ()) -> dict[str, Any]:
    """The `--set` settings of `args` as `load_preset` overrides, checked before any work, and with them the settings
    of every run the script will train: settings that clash (a variant's orbit with `--set
    camera.parameterization=camera`) fail otherwise when that run starts, after the runs before it, and TrainConfig's
    message names `warpbags train`'s options, not what the script chose.

    Args:
        args: parsed options with `preset` and `settings` (`add_training_options`).
        fixed: the fields the script sets itself ("name" or "group.name"), each with where its value comes from
            ("from --views"); a `--set` of one of them is an error instead of being ignored or clashing.
        runs: the script's own settings of each run, merged over the overrides (`merge_settings`), each labelled by
            what chose them ("--variants frozen-orbit: its settings ...").

    Raises:
        WarpbagsError: a malformed `--set`, one of `fixed`, an unknown preset or field, or a bad value; for a run,
            its label first, then the preset and overrides it was merged with.
    """
    overrides = parse_settings(args.settings)
    for name, source in (fixed or {}).items():
        group, _, field = name.rpartition(".")
        settings = overrides.get(group, {}) if group else overrides
        if isinstance(settings, dict) and field in settings:
            raise WarpbagsError(f"--set {name}: this benchmark sets {name} itself ({source})")
    runs = list(runs)
    if not runs:  # with runs, only the merged settings are checked: `--set views_per_step=6` is right for --views 6
        load_preset(args.preset, **overrides)
    given = f"--preset {args.preset}" + (f" and --set {overrides}" if overrides else "")
    for label, run in runs:
        try:
            load_preset(args.preset, **merge_settings(overrides, run))
        except WarpbagsError as error:
            raise WarpbagsError(f"{label} with {given}: {error}") from None
    return overrides


def quiet_trainer(scene, settings: dict, preset: str, folder: Path) -> Trainer:
    """A Trainer of `preset` with `settings` on `scene`, writing into `folder`, that logs nothing (the start
    procedures have run; the run files are not written yet)."""
    config = load_preset(preset, **settings)
    return Trainer(training_scene(scene, config), config, folder, log=lambda message: None)


def timed_training(trainer: Trainer) -> float:
    """Write `trainer`'s run files and train it to the end; returns the minutes of the training iterations alone."""
    trainer.write_run_files()
    started = time.perf_counter()
    trainer.train()
    return (time.perf_counter() - started) / 60


def write_json(path: Path, data: Any, indent: int = 1) -> None:
    """Write `data` to `path` as strict JSON (a NaN, e.g. a PSNR not measured, as null), creating its folder. The
    scripts rewrite it after every row; the write is atomic, so a run stopped mid-write leaves the last rows."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as temporary:
        temporary.write_text(finite_json(data, indent=indent))
