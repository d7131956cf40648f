"""The `warpbags train` options that set TrainConfig fields, as one table.

The typer options of `warpbags train`, their help (the field's description from its dataclass docstring and the
presets' defaults) and the rule that every field is given once (by an option or by `--set`, not both) are all
derived from `TRAIN_OPTIONS`; a new option is one row here.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Literal, Optional, get_args, get_origin, get_type_hints

import typer
from rich.markup import escape

from warpbags.configs.train import PRESETS, TrainConfig, check_repairer_used, load_preset, parse_settings
from warpbags.data.catalog import DATA_ROOT_SCENES
from warpbags.errors import WarpbagsError


@dataclass(frozen=True)
class ConfigOption:
    """One command-line option that sets one TrainConfig field.

    Attributes:
        flag: the option, e.g. "--rot-noise-deg"; its parameter name is the flag without dashes.
        path: the field it sets, "name" or "group.name", as `--set` spells it.
        sets: for an option that takes no value (a flag), the value it gives the field, e.g. False for
            `--no-pose-opt`; None: the option takes a value of the field's type.
        help: what the option does, where the field's own description does not say it (a flag's meaning);
            empty: the field's description from its dataclass docstring.
        short: a one-letter alias, e.g. "-r".
        follows: the field whose value this one takes when neither the option nor `--set` gives it (e.g. the noise
            seed follows the seed); None: the preset's value.
    """

    flag: str
    path: str
    sets: Any = None
    help: str = ""
    short: str | None = None
    follows: str | None = None

    @property
    def parameter(self) -> str:
        return self.flag.lstrip("-").replace("-", "_")


TRAIN_OPTIONS = (
    ConfigOption("--views", "views", help="Training views, >= 2: the scene's sparse_N split, else a farthest-point "
                                          "choice."),
    ConfigOption("--iters", "iters"),
    ConfigOption("--rounds", "rounds"),
    ConfigOption("--init", "init"),
    ConfigOption("--depth-loss", "depth_loss"),
    ConfigOption("--blur-px", "blur_sigma_px"),
    ConfigOption("--blur-until", "blur_until"),
    ConfigOption("--pose-opt-start", "pose_opt_start"),
    ConfigOption("--rot-noise-deg", "rot_noise_deg"),
    ConfigOption("--rot-noise-fixed", "rot_noise_fixed", sets=True,
                 help="Turn every camera by exactly --rot-noise-deg (about a random axis), not by a normal angle of "
                      "that std."),
    ConfigOption("--trans-noise", "trans_noise"),
    ConfigOption("--no-pose-opt", "pose_opt", sets=False, help="Keep poses fixed (GaussianObject baseline)."),
    ConfigOption("--fix-first-camera", "camera.fix_first_camera", sets=True,
                 help="Keep camera 0 at its given pose as the gauge (default: every camera is optimized; errors "
                      "after sim(3) alignment)."),
    ConfigOption("--coherence-iters", "camera.coherence_iters"),
    ConfigOption("--camera-param", "camera.parameterization"),
    ConfigOption("--orbit-from-round", "camera.orbit_from_round"),
    ConfigOption("--round-anchor", "camera.round_anchor"),
    ConfigOption("--hypotheses-round", "camera.hypotheses_round"),
    ConfigOption("--repair-iters", "repair.iters"),
    ConfigOption("--no-repair", "repair.iters", sets=0, help="Skip the repair stage."),
    ConfigOption("--repairer", "repair.repairer"),
    ConfigOption("--seed", "seed"),
    ConfigOption("--noise-seed", "noise_seed", follows="seed"),
    ConfigOption("--resolution", "resolution", short="-r"),
    ConfigOption("--max-image-size", "max_image_size"),
)

# The help of `--data-root`, which `warpbags train` and `warpbags sweep` hand to `check_data_root`.
DATA_ROOT_HELP = (f"Folder holding the datasets of the presets {', '.join(DATA_ROOT_SCENES)} (default: $WARPBAGS_DATA, "
                  "else data/); refused with any other scene.")

# "name: text" or "name, other: text" at the start of a docstring entry (Google style); deeper lines continue it.
_ENTRY = re.compile(r"^( +)([a-z_][a-z0-9_]*(?:, [a-z_][a-z0-9_]*)*): (.*)$")


def field_descriptions(config_class: type) -> dict[str, str]:
    """Each field's description in a config dataclass's docstring, by field name.

    Entries are Google-style `name: text` (or `name, other: text`, shared) lines, continued on more deeply
    indented lines; they may sit under any heading (`Attributes:`, or RepairConfig's groups).
    """
    descriptions: dict[str, list[str]] = {}
    current: list[str] | None = None
    indent = 0
    for line in inspect.cleandoc(config_class.__doc__ or "").splitlines():
        entry = _ENTRY.match(line)
        if entry and (current is None or len(entry[1]) <= indent):
            indent, current = len(entry[1]), [entry[3]]
            for name in entry[2].split(", "):
                descriptions[name] = current
        elif current is not None and line.strip() and len(line) - len(line.lstrip()) > indent:
            current.append(line.strip())
        else:
            current = None
    return {name: " ".join(words) for name, words in descriptions.items()}


def _owner(path: str) -> tuple[type, str]:
    """The config dataclass holding the field at `path`, and the field's name."""
    *groups, name = path.split(".")
    owner: type = TrainConfig
    for group in groups:
        owner = get_type_hints(owner)[group]
    if name not in {item.name for item in dataclasses.fields(owner)}:
        raise KeyError(f"TrainConfig has no field {path}")
    return owner, name


def field_type(path: str) -> type:
    """The type an option for the field at `path` parses: bool, int, float or str (a Literal's choices are
    checked by `TrainConfig.validate`, which names the option)."""
    owner, name = _owner(path)
    hint = get_type_hints(owner)[name]
    if get_origin(hint) is Literal:
        return type(get_args(hint)[0])
    choices = [arg for arg in get_args(hint) if arg is not type(None)] if get_origin(hint) is not None else [hint]
    if len(choices) != 1 or choices[0] not in (bool, int, float, str):
        raise TypeError(f"{path}: {hint} has no command-line option type")
    return choices[0]


def field_value(config: TrainConfig, path: str) -> Any:
    """The value of the field at `path` ("name" or "group.name") in `config`."""
    value: Any = config
    for name in path.split("."):
        value = getattr(value, name)
    return value


def _text(value: Any) -> str:
    return "none" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def option_help(option: ConfigOption) -> str:
    """The option's help: what it does, the field it sets and the presets' values of that field."""
    owner, name = _owner(option.path)
    text = option.help or field_descriptions(owner).get(name, "")
    text = text[:1].upper() + text[1:]
    defaults = {preset: field_value(make(), option.path) for preset, make in PRESETS.items()}
    if option.follows:
        default = f"default: the value of {option.follows}"
    elif len(set(map(repr, defaults.values()))) == 1:
        default = f"preset default: {_text(next(iter(defaults.values())))}"
    else:
        default = "preset default: " + ", ".join(f"{preset} {_text(value)}" for preset, value in defaults.items())
    sets = option.path if option.sets is None else f"{option.path}={_text(option.sets)}"
    return escape(f"{text} (sets {sets}; {default})")


def typer_parameters() -> list[inspect.Parameter]:
    """One keyword parameter per TRAIN_OPTIONS row for a typer command's signature: a flag (False = not given)
    or an optional value (None = not given, the preset's)."""
    parameters = []
    for option in TRAIN_OPTIONS:
        names = (option.flag, option.short) if option.short else (option.flag,)
        if option.sets is not None:
            default, annotation = typer.Option(False, *names, help=option_help(option), show_default=False), bool
        else:
            default = typer.Option(None, *names, help=option_help(option))
            annotation = Optional[field_type(option.path)]
        parameters.append(inspect.Parameter(option.parameter, inspect.Parameter.KEYWORD_ONLY, default=default,
                                            annotation=annotation))
    return parameters


def with_train_options(after: str) -> Callable[[Callable], Callable]:
    """A decorator: the command's signature, which typer reads, gets the TRAIN_OPTIONS parameters after its
    keyword-only parameter `after`, in place of its `**kwargs` (which receives them)."""

    def decorate(command: Callable) -> Callable:
        signature = inspect.signature(command, eval_str=True)
        own = [parameter for parameter in signature.parameters.values()
               if parameter.kind is not inspect.Parameter.VAR_KEYWORD]
        at = [parameter.name for parameter in own].index(after) + 1
        command.__signature__ = signature.replace(parameters=[*own[:at], *typer_parameters(), *own[at:]])
        return command

    return decorate


def _flattened(values: dict[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, value in values.items():
        if isinstance(value, dict):
            yield from _flattened(value, f"{prefix}{key}.")
        else:
            yield prefix + key, value


def _put(values: dict[str, Any], path: str, value: Any) -> None:
    *groups, name = path.split(".")
    for group in groups:
        values = values.setdefault(group, {})
    values[name] = value


def _has(values: dict[str, Any], path: str) -> bool:
    *groups, name = path.split(".")
    for group in groups:
        values = values.get(group)
        if not isinstance(values, dict):
            return False
    return name in values


def _overlap(path: str, other: str) -> bool:
    return path == other or path.startswith(other + ".") or other.startswith(path + ".")


def config_overrides(given: dict[str, Any], settings: list[str]) -> dict[str, Any]:
    """`load_preset` overrides from the TRAIN_OPTIONS given and the `--set` items, each field from one source.

    Args:
        given: TRAIN_OPTIONS parameter name -> parsed value (None, or False for a flag: not given).
        settings: `--set` items, "name=value" or "group.name=value" with JSON values.

    Returns:
        {"name": value, "group": {"name": value}} for the fields given.

    A later `--set` of a field replaces an earlier one (a command line can extend a base one), as `parse_settings`
    does.

    Raises:
        WarpbagsError: a field given by two options or by an option and a `--set`, or a `--set` item without "=".
    """
    options: dict[str, tuple[str, Any]] = {}  # field path -> (the option as given, value)
    for option in TRAIN_OPTIONS:
        value = given.get(option.parameter)
        if option.sets is None and value is not None:
            value_given = (f"{option.flag} {value}", value)
        elif option.sets is not None and value:
            value_given = (option.flag, option.sets)
        else:
            continue
        _check_once(options, option.path, value_given[0])
        options[option.path] = value_given
    settings_given: dict[str, tuple[str, Any]] = {}
    for item in settings:
        for path, value in _flattened(parse_settings([item])):
            _check_once(options, path, f"--set {item}")
            settings_given = {other: earlier for other, earlier in settings_given.items() if not _overlap(path, other)}
            settings_given[path] = (f"--set {item}", value)
    overrides: dict[str, Any] = {}
    for path, (_, value) in {**options, **settings_given}.items():
        _put(overrides, path, value)
    return overrides


def _check_once(given: dict[str, tuple[str, Any]], path: str, source: str) -> None:
    """Raise if a field of `given` (field path -> (source, value)) is, contains or is inside the field at `path`."""
    for other, (other_source, _) in given.items():
        if _overlap(path, other):
            raise WarpbagsError(f"{other_source} and {source} both set {min(path, other, key=len)}; give one")


def resumed_config(saved: TrainConfig, preset: str | None, given: dict[str, Any], settings: list[str],
                   read_at: int | None = None) -> TrainConfig:
    """`saved`, the config of the run that `warpbags train --resume` continues, once the preset and the TRAIN_OPTIONS
    and `--set` items given alongside agree with it: a run does not change its schedule half-way, and the same
    command line that started it may be given again.

    Args:
        read_at: the resolution factor the run read its images at (config.json's): a run that left the factor to the
            scene (`resolution` None) accepts it named (`-r 8` for a preset read at 1/8), which opens the same images.

    Raises:
        WarpbagsError: a preset, option or `--set` value that differs from the run's.
    """
    if preset is not None and preset != saved.preset:
        raise WarpbagsError(f"--resume: the run was trained with --preset {saved.preset}, not {preset}; drop --preset "
                            "or start a new run")
    overrides = config_overrides(given, settings)
    if saved.resolution is None and read_at is not None and overrides.get("resolution") == read_at:
        del overrides["resolution"]
    asked = saved.replaced(**overrides)  # checked against the run's own config (views_per_step <= views, ...)
    for path, _ in _flattened(overrides):
        if field_value(asked, path) != field_value(saved, path):
            if path == "resolution" and saved.resolution is None and read_at is not None:
                raise WarpbagsError(f"--resume: the run read its images at the scene's resolution factor {read_at}, "
                                    f"not {asked.resolution}; drop that option or start a new run")
            raise WarpbagsError(f"--resume: the run was trained with {path}={_text(field_value(saved, path))}, not "
                                f"{_text(field_value(asked, path))}; drop that option or start a new run")
    return saved


def train_config(preset: str, given: dict[str, Any], settings: list[str]) -> TrainConfig:
    """The preset `preset` with the TRAIN_OPTIONS given and the `--set` items applied (`config_overrides`); a field
    with `follows` that neither gives takes the value of the field it follows.

    Raises:
        WarpbagsError: a field given twice, an unknown field, a value of the wrong type or out of range.
    """
    overrides = config_overrides(given, settings)
    config = load_preset(preset, **overrides)
    check_repairer_used(overrides, config)
    following = [option for option in TRAIN_OPTIONS if option.follows and not _has(overrides, option.path)]
    for option in following:
        _put(overrides, option.path, field_value(config, option.follows))
    return load_preset(preset, **overrides) if following else config
