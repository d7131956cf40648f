"""The command line's layout: `warpbags train`'s config options come from one table (TRAIN_OPTIONS), each field is
given once (its option or `--set`), and every command group registers through `warpbags.cli.main`."""

from __future__ import annotations

import dataclasses
import io
import json
import re
import subprocess
import sys
import typing

import pytest
import typer.main
from typer.testing import CliRunner

from warpbags.cli import train as train_command
from warpbags.cli.common import parse_numbers
from warpbags.cli.main import COMMAND_GROUPS, app
from warpbags.cli.train_options import TRAIN_OPTIONS, field_descriptions, field_type, field_value, resumed_config
from warpbags.configs.train import PRESETS, TrainConfig, load_preset, quick
from warpbags.data import SyntheticOptions, ensure_synthetic_scene
from warpbags.errors import WarpbagsError

runner = CliRunner()
# Options of `warpbags train` that are not TrainConfig fields.
RUN_OPTIONS = {"--preset", "--set", "--device", "--data-root", "--out", "--resume", "--log-every"}
# Values no preset has, valid where the type alone does not say what is.
SAMPLES = {"resolution": 2, "repair.repairer": "package.module:factory"}


class Stop(Exception):
    """Raised in place of loading the scene: the config the command built is all these tests need."""


@pytest.fixture
def parsed(monkeypatch):
    """`parsed(*arguments, scene="scene")`: the TrainConfig that `warpbags train scene *arguments` would train with;
    `parsed.loads` lists the (scene, data_root) each call handed the loader."""
    configs, loads = [], []

    def training_scene(scene, config, data_root=None, log=print):
        configs.append(config)
        loads.append((scene, data_root))
        raise Stop

    monkeypatch.setattr(train_command, "training_scene", training_scene)

    def parse(*arguments: str, scene: str = "scene") -> TrainConfig:
        result = runner.invoke(app, ["train", scene, *arguments])
        assert isinstance(result.exception, Stop), result.output
        return configs[-1]

    parse.loads = loads
    return parse


def sample(path: str):
    """A value for the field at `path` that the quick preset does not have."""
    if path in SAMPLES:
        return SAMPLES[path]
    owner = TrainConfig
    for group in path.split(".")[:-1]:
        owner = typing.get_type_hints(owner)[group]
    hint = typing.get_type_hints(owner)[path.split(".")[-1]]
    default = field_value(quick(), path)
    if typing.get_origin(hint) is typing.Literal:
        return next(choice for choice in typing.get_args(hint) if choice != default)
    return {int: default + 1, float: default + 1.5}[field_type(path)]


def command_line(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def one_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


def test_the_train_options_are_the_table_and_the_run_options():
    command = typer.main.get_command(app).commands["train"]
    flags = {name for parameter in command.params for name in parameter.opts if name.startswith("--")}
    assert flags == {option.flag for option in TRAIN_OPTIONS} | RUN_OPTIONS


def description(option) -> str:
    """The table's help for `option`, else its field's entry in the config dataclass's docstring."""
    *groups, name = option.path.split(".")
    owner = type(field_value(TrainConfig(), ".".join(groups))) if groups else TrainConfig
    return option.help or field_descriptions(owner).get(name, "")


@pytest.mark.parametrize("option", TRAIN_OPTIONS, ids=lambda option: option.flag)
def test_each_table_option_is_in_the_help_with_its_field(option):
    result = runner.invoke(app, ["train", "--help"], env={"COLUMNS": "1000"})
    assert result.exit_code == 0, result.output
    line = next(line for line in result.output.splitlines() if f" {option.flag} " in line)
    assert f"sets {option.path}" in line and description(option)[1:40] in line, line


# Options that are refused alone (`TrainConfig.validate`): what each is given beside it here.
# a blur shrinks to none over blur_until iterations; the fixed noise angle is --rot-noise-deg
COMPANIONS = {"blur_sigma_px": ["--blur-until", "10"], "rot_noise_fixed": ["--rot-noise-deg", "10"]}


@pytest.mark.parametrize("option", TRAIN_OPTIONS, ids=lambda option: option.flag)
def test_each_table_option_sets_its_field_as_set_does(parsed, option):
    value = sample(option.path) if option.sets is None else option.sets
    # a preset the option changes (--no-repair changes paper's, not quick's)
    preset = next(name for name, make in PRESETS.items() if field_value(make(), option.path) != value)
    arguments = [option.flag] + ([] if option.sets is not None else [command_line(value)])
    companions = COMPANIONS.get(option.path, [])
    config = parsed("--preset", preset, *arguments, *companions)
    assert field_value(config, option.path) == value
    assert parsed("--preset", preset, "--set", f"{option.path}={json.dumps(value)}", *companions) == config


@pytest.mark.parametrize("option", TRAIN_OPTIONS, ids=lambda option: option.flag)
def test_an_option_and_a_set_of_its_field_are_one_error_line(option):
    value = sample(option.path) if option.sets is None else option.sets
    arguments = [option.flag] + ([] if option.sets is not None else [command_line(value)])
    result = runner.invoke(app, ["train", "scene", *arguments, "--set", f"{option.path}={json.dumps(value)}"])
    message = one_line(result)
    assert f"both set {option.path}; give one" in message and option.flag in message and "--set" in message


@pytest.mark.parametrize("arguments, message", [
    (["--no-repair", "--repair-iters", "5"], "--repair-iters 5 and --no-repair both set repair.iters; give one"),
    (["--set", "repair=3", "--no-repair"], "--no-repair and --set repair=3 both set repair; give one"),
    (["--set", "views"], "expected name=value"),
    (["--set", ".pose=1"], "--set '.pose=1': expected name=value"),  # was "unknown training option(s): " and nothing
    (["--set", "lr.=1"], "--set 'lr.=1': expected name=value"),
    (["--set", "nonsense=1"], "unknown training option(s): nonsense"),
    (["--set", "views=1"], "--views must be >= 2, got 1"),
    # the preset only relabelled the run; a top-level null was dropped as "the preset's value", silently
    (["--set", 'preset="paper"'], "the preset is chosen by --preset"),
    (["--set", "seed=null"], "--set 'seed=null': null is not a value of seed; leave it out for the preset's"),
])
def test_fields_given_twice_and_bad_settings_are_one_line(arguments, message):
    assert message in one_line(runner.invoke(app, ["train", "scene", *arguments]))


def test_set_reaches_fields_with_an_option_and_the_noise_seed_follows_the_seed(parsed):
    assert parsed("--set", "views=6").views == 6  # a field with its own option, given once
    assert parsed().noise_seed == 0
    assert parsed("--seed", "3").noise_seed == 3
    assert parsed("--set", "seed=3").noise_seed == 3
    assert parsed("--seed", "3", "--noise-seed", "5").noise_seed == 5
    assert parsed("--set", "noise_seed=5").seed == 0
    assert parsed("--preset", "paper") == PRESETS["paper"]()


def test_data_root_reaches_the_scene_loader(tmp_path, parsed):
    """`--data-root` is not a config field: only the loader's call carries it to the data-root presets' folders."""
    parsed("--data-root", str(tmp_path), "--views", "4", scene="kitchen")
    assert parsed.loads[-1] == ("kitchen", tmp_path)
    parsed(scene="kitchen")
    assert parsed.loads[-1] == ("kitchen", None)  # left out: the loader's own default ($WARPBAGS_DATA, data/)


@pytest.mark.parametrize("scene, root, message", [
    ("scene", "root", "--data-root is read only by the presets ethiopianhead, kitchen, moldgoldcape, not by scene "
                      "'scene': leave it out"),
    ("synthetic", "root", "--data-root is read only by the presets ethiopianhead, kitchen, moldgoldcape, not by scene "
                          "'synthetic': leave it out"),
    ("kitchen", "missing", "--data-root {root}: not a folder"),
])
def test_a_data_root_the_scene_does_not_read_is_one_line(tmp_path, parsed, scene, root, message):
    """`--data-root` was ignored, silently, unless the scene was a data-root preset, even a folder that does not exist;
    the help said only "Folder holding datasets." (`warpbags sweep` checks it through the same helper)."""
    (tmp_path / "root").mkdir()
    result = runner.invoke(app, ["train", scene, "--data-root", str(tmp_path / root)])
    assert one_line(result) == f"error: {message.format(root=tmp_path / root)}"
    assert not parsed.loads  # refused before the scene is read
    result = runner.invoke(app, ["info", scene, "--data-root", str(tmp_path / root)])  # `info` takes it alike
    assert one_line(result) == f"error: {message.format(root=tmp_path / root)}"
    help_text = " ".join(runner.invoke(app, ["train", "--help"], env={"COLUMNS": "1000"}).output.split())
    assert "datasets of the presets ethiopianhead, kitchen, moldgoldcape (default: $WARPBAGS_DATA, else data/); " \
           "refused with any other scene" in help_text


def test_warpbags_data_in_the_environment_is_no_error_for_a_scene_folder(tmp_path, parsed, monkeypatch):
    """$WARPBAGS_DATA, which the benches read the data-root presets through, is a default that may stay set (even to a
    folder that is gone) while a scene folder trains: only the --data-root option given is checked."""
    monkeypatch.setenv("WARPBAGS_DATA", str(tmp_path / "gone"))
    parsed(scene=str(tmp_path))
    assert parsed.loads[-1] == (str(tmp_path), None)


def test_train_on_a_terminal_shows_the_progress_bar_to_its_last_step(tmp_path, monkeypatch):
    """A terminal gets a progress bar (`_train_with_progress_bar`), which no CliRunner or subprocess test ever drew:
    neither is a terminal. With the command's console forced to one, a tiny run (with the turn search's trial rounds,
    which the bar counts as steps) ends with the bar at its total, no log lines, and the run's files written."""
    from rich.console import Console

    scene = ensure_synthetic_scene(SyntheticOptions(views=8, width=48, height=48), cache_dir=tmp_path / "cache")
    screen = io.StringIO()
    console = Console(file=screen, force_terminal=True, width=200, highlight=False, markup=False)
    monkeypatch.setattr(train_command, "stdout", console)
    out = tmp_path / "run"
    result = runner.invoke(app, ["train", str(scene), "--iters", "6", "--max-image-size", "32", "--set",
                                 "init_points=300", "--set", "camera.coherence_iters=0", "--out", str(out)])
    shown = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", screen.getvalue())
    assert result.exit_code == 0, (result.output, shown)
    assert "iter " not in result.output  # the log lines of a run without a terminal
    counts = re.findall(r"train .*? (\d+)/(\d+) ", shown)  # each redraw of the bar, the last one last
    assert counts and counts[-1][0] == counts[-1][1] and int(counts[-1][1]) > 6, shown  # 6 + the trial rounds
    assert f"wrote {out}" in " ".join(shown.split())
    assert (out / "gaussians.ply").is_file() and (out / "poses_final.npy").is_file()


def test_the_short_resolution_option_sets_the_resolution(parsed):
    assert parsed("-r", "2").resolution == 2
    assert parsed("-r", "2") == parsed("--resolution", "2")


def test_a_later_set_replaces_an_earlier_one(parsed):
    assert parsed("--set", "seed=1", "--set", "seed=2").seed == 2
    assert parsed("--set", "lr.pose=0.1", "--set", 'lr={"pose": 0.2}').lr.pose == 0.2
    # a group's JSON object sets its fields one by one
    assert parsed("--set", 'lr={"pose": 0.2, "sh_dc": 0.1}', "--set", "lr.pose=0.3").lr == dataclasses.replace(
        quick().lr, pose=0.3, sh_dc=0.1)


def test_every_table_option_is_described():
    assert all(description(option) for option in TRAIN_OPTIONS)


def test_every_command_group_registers_through_main():
    names = [command.name for command in app.registered_commands]
    assert names == ["info", "synth", "train", "eval", "agree", "export", "render", "sweep", "view"]
    assert all(callable(group.register) for group in COMMAND_GROUPS)
    for name in names:
        result = runner.invoke(app, [name, "--help"])
        assert result.exit_code == 0 and "Usage" in result.output, (name, result.output)


def test_python_dash_m_runs_the_command_line():
    result = subprocess.run([sys.executable, "-m", "warpbags.cli.main", "--help"], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0 and "train" in result.stdout, result.stderr


def test_parse_numbers_reads_comma_separated_numbers_and_skips_empty_items():
    assert parse_numbers("5,10,15", "--rot") == [5.0, 10.0, 15.0]
    assert parse_numbers("0,1,", "--seeds", int) == [0, 1]
    assert parse_numbers("2.5", "--rot") == [2.5]


@pytest.mark.parametrize("text, kind, message", [
    ("a", float, "--opt 'a': 'a' is not a number"),
    ("1,x", int, "--opt '1,x': 'x' is not an integer"),
    ("1.5", int, "--opt '1.5': '1.5' is not an integer"),
    (",", int, "--opt ',': expected comma-separated numbers, got none"),
    ("", float, "--opt '': expected comma-separated numbers, got none"),
    ("4_6", int, "--opt '4_6': '4_6' is not an integer"),  # Python's digit grouping: a typo of 4,6 read as 46
    ("1_0.5", float, "--opt '1_0.5': '1_0.5' is not a number"),
])
def test_parse_numbers_names_the_option_and_the_bad_text(text, kind, message):
    with pytest.raises(WarpbagsError) as error:
        parse_numbers(text, "--opt", kind)
    assert str(error.value) == message


def test_a_resumed_run_checks_options_given_again_against_its_own_config():
    """`views_per_step <= views` holds for the run (9 views), not for its preset's default (4)."""
    saved = load_preset("paper", views=9, views_per_step=6)
    assert resumed_config(saved, None, {}, ["views_per_step=6"]) is saved


def test_a_command_runs_with_its_error_stream_closed():
    """With descriptor 2 closed (a daemon, `2>&-`) sys.stderr is None: Warp's quiet start flushed it and every
    command exited 1 without a word."""
    import shlex

    command = f"{shlex.quote(sys.executable)} -m warpbags.cli.main info maryrose 2>&-"
    result = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "maryrose" in result.stdout, result.stdout
