"""`warpbags sweep`'s own checks: settings it refuses are named in the sweep's terms, before any folder is made; the
eval.json of a finished run it reads is checked, and a metric held as null shows as n/a."""

from __future__ import annotations

import json
import math
import shutil

import pytest
import torch
from typer.testing import CliRunner

from warpbags.cli.main import app
from warpbags.data import SyntheticOptions, ensure_synthetic_scene
from warpbags.errors import WarpbagsError
from warpbags.files import finite_json
from warpbags.sweep import SweepSpec, combination_config, make_executor, run_sweep, sweep_runs

runner = CliRunner()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return ensure_synthetic_scene(SyntheticOptions(views=16, width=64, height=64),
                                  cache_dir=tmp_path_factory.mktemp("cache"))


def evaluation(psnr: float = 20.0, rot_final: float = 1.0) -> dict:
    """The parts of an eval.json (`evaluate_run`) that a sweep's row reads; each stage's and each row's numbers
    differ, so that a row that read the wrong one would show it."""
    poses = {stage: {"rotation_deg_mean": rotation, "translation_mean": translation}
             for stage, rotation, translation in (("initial", 5.0, 0.05), ("final", rot_final, 0.01))}
    images = {"mean": {"psnr": psnr, "ssim": 0.9, "flip": 0.1, "lpips": None}, "per_view": []}
    refined = {"mean": {**images["mean"], "psnr": psnr + 1.5}, "per_view": []}
    return {"alignment": "procrustes", "poses": {"procrustes": poses}, "images": images,
            "images_after_test_pose_refinement": {"iters": 2, **refined}}


def write_evaluation(folder, report: dict) -> None:
    folder.mkdir(parents=True)
    (folder / "eval.json").write_text(finite_json(report))  # as evaluate_run writes it: NaN and infinity as null


def test_iters_below_the_presets_rounds_names_iters_not_rounds(tmp_path, monkeypatch):
    """The quick preset trains in 3 rounds: `--iters 2` said `--rounds must be in [1, iters], got 3`, an option the
    sweep does not have. The message names --iters and the preset's rounds, before the scene is read or a folder is
    made."""
    out = tmp_path / "s"
    result = runner.invoke(app, ["sweep", "maryrose", "--iters", "2", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "--iters must be >= 3: the quick preset trains in 3 rounds" in lines[0] and "--rounds" not in lines[0]
    assert not out.exists()

    def scene_read(*args, **kwargs):
        raise WarpbagsError("the scene was read")

    monkeypatch.setattr("warpbags.sweep.open_scene", scene_read)
    with pytest.raises(WarpbagsError, match="^--iters must be >= 1: the paper preset trains in 1 round of"):
        run_sweep(SweepSpec(scene="maryrose", out=out, preset="paper", overrides=(("iters", 0),)))
    # as many iterations as rounds pass this check (and go on to read the scene); so do the preset's own
    for overrides in ((("iters", 3),), ()):
        with pytest.raises(WarpbagsError, match="the scene was read"):
            run_sweep(SweepSpec(scene="maryrose", out=out, overrides=overrides))
    assert not out.exists()


def test_null_metrics_of_finished_runs_show_as_na_and_stay_out_of_the_plots(scene, tmp_path):
    """A finished run's eval.json holds an infinite PSNR (an exact render) or a NaN rotation error as null: the
    sweep's table printed `{None:.2f}` (a TypeError traceback) and its plot took np.mean of None. The table shows n/a
    for them, sweep.json keeps null, and the plots average the other runs' values."""
    out = tmp_path / "sweep"
    write_evaluation(out / "baseline-4v-rot5-seed0", evaluation(psnr=math.inf))
    write_evaluation(out / "bags-4v-rot5-seed0", evaluation(psnr=25.0, rot_final=math.nan))
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "skip baseline-4v-rot5-seed0 (done)" in result.output and result.output.count("n/a") == 3, result.output
    rows = json.loads((out / "sweep.json").read_text())
    assert [(row["psnr"], row["psnr_refined"], row["rot_err_final"]) for row in rows] == [(None, None, 1.0),
                                                                                          (25.0, 26.5, None)]
    assert all((row["rot_err_initial"], row["trans_err_initial"], row["trans_err_final"]) == (5.0, 0.05, 0.01)
               for row in rows)
    for name in ("psnr_vs_noise.png", "pose_error_vs_noise.png"):
        assert (out / name).stat().st_size > 100, name


@pytest.mark.parametrize("content, named", [
    ("{\"alignment\": \"procrustes\", ", "unreadable (Expecting"),  # cut short
    (json.dumps({key: value for key, value in evaluation().items() if key != "poses"}), "no poses (not an evaluation"),
    (json.dumps({**evaluation(), "alignment": "pairwise"}), "no poses.pairwise (not an evaluation"),
    (json.dumps({**evaluation(), "images": {"mean": {"psnr": "high", "ssim": 0.9}}}),
     "images.mean.psnr is 'high', not a number"),
    ("[1, 2]", "no alignment (not an evaluation"),
])
def test_unusable_eval_json_of_a_finished_run_is_one_line_before_anything_trains(scene, tmp_path, monkeypatch,
                                                                                content, named):
    """A malformed or incomplete eval.json (by hand, another tool, an older warpbags) was a JSONDecodeError or
    KeyError traceback, and only after the runs before it had trained. It is one line naming the file, before any
    run trains; the sweep writes no tables. (The sweep does not evaluate the run again over it: evaluate_run writes
    eval.json atomically, so it is no file of a sweep cut short; the message says to remove it.)"""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    out = tmp_path / "sweep"
    (out / "bags-4v-rot5-seed0").mkdir(parents=True)  # after baseline-4v-rot5-seed0, which is not done
    (out / "bags-4v-rot5-seed0" / "eval.json").write_text(content)
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"{out / 'bags-4v-rot5-seed0' / 'eval.json'}: {named}" in lines[0], lines[0]
    assert lines[0].endswith("remove it and run the sweep again to evaluate the run anew"), lines[0]
    assert sorted(path.name for path in out.iterdir()) == ["bags-4v-rot5-seed0"]


def test_a_scene_whose_runs_would_have_no_test_view_is_one_line_before_anything_trains(scene, tmp_path, monkeypatch):
    """Evaluating a run needs held-out views: a capture whose every 8th view is one of the sweep's training views
    (no sparse_test.txt) trained the first run to the end and then stopped at its evaluation. It is one line before
    any run trains."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    capture = tmp_path / "capture"
    shutil.copytree(scene, capture)
    (capture / "sparse_test.txt").unlink()
    (capture / "sparse_4.txt").write_text("0\n8\n3\n12\n")  # 16 views: every 8th is 0 and 8
    out = tmp_path / "sweep"
    result = runner.invoke(app, ["sweep", str(capture), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "has no test split" in lines[0] and "baseline-4v-rot5-seed0" in lines[0], lines[0]
    assert not out.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_cuda_is_one_line_before_the_sweep_folder_is_made(scene, tmp_path):
    """The local executor's runs use this machine: --device cuda here failed only in the first run, after its
    progress line and with the sweep's folder made."""
    out = tmp_path / "sweep"
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--device", "cuda",
                                 "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "no CUDA device" in lines[0], result.output
    assert not out.exists()


@pytest.mark.parametrize("blocker, named", [
    ("bags-4v-rot5-seed0/notes.txt", "bags-4v-rot5-seed0 is not empty (notes.txt) and holds no run to --resume"),
    ("sweep.csv/", "sweep.csv is a folder, not a file for the sweep's tables and figures"),
    ("curves.png/", "curves.png is a folder, not a file for the sweep's tables and figures"),
])
def test_a_folder_in_the_way_of_a_run_or_the_tables_is_one_line_before_anything_trains(scene, tmp_path, monkeypatch,
                                                                                        blocker, named):
    """A run's folder holding other files was refused when its turn came, after the runs before it had trained; a
    folder named as a table or figure was a traceback after every run. Both are one line before any run trains."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    out = tmp_path / "sweep"
    path = out / blocker.rstrip("/")
    if blocker.endswith("/"):
        path.mkdir(parents=True)
    else:
        path.parent.mkdir(parents=True)
        path.write_text("mine")
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and named in " ".join(result.output.split()), result.output


def test_ray_options_without_ray_are_named_in_one_line():
    for options, message in ((dict(cpus_per_run=2), "--cpus-per-run needs --executor ray"),
                             (dict(address="auto", gpus_per_run=1), "--address, --gpus-per-run need --executor ray")):
        with pytest.raises(WarpbagsError, match=message):
            make_executor("local", **options)


def test_set_reaches_every_run_and_fields_the_sweep_sets_are_refused(tmp_path, monkeypatch):
    """`warpbags sweep` had no --set: a sweep could not vary a TrainConfig field that has no sweep option. Every run
    takes the items (with --iters and --repair-iters); the fields a sweep sets per run are one line each."""
    specs = []
    monkeypatch.setattr("warpbags.cli.sweep.run_sweep", lambda spec, **kwargs: specs.append(spec) or [])
    out = tmp_path / "s"
    result = runner.invoke(app, ["sweep", "maryrose", "--rot-noises", "5,10", "--views", "4", "--iters", "30",
                                 "--repair-iters", "4", "--set", "lr.pose=0.005", "--set", "repair.fit_steps=7",
                                 "--set", "camera.coherence_iters=0", "--out", str(out)])
    assert result.exit_code == 0, result.output
    (spec,) = specs
    configs = [combination_config(spec, run) for run in sweep_runs(spec)]
    assert len(configs) == 4 and {config.pose_opt for config in configs} == {True, False}
    for config in configs:
        assert (config.iters, config.repair.iters, config.repair.fit_steps) == (30, 4, 7)
        assert (config.lr.pose, config.camera.coherence_iters) == (0.005, 0)
    for items, message in ((["--set", "views=6"], "--set views: a sweep sets it per run, by --views"),
                           (["--set", "noise_seed=3"], "--set noise_seed: a sweep sets it per run, by --seeds"),
                           (["--set", "pose_opt=false"], "--set pose_opt: a sweep sets it per run"),
                           (["--iters", "30", "--set", "iters=40"], "--iters 30 and --set iters=40 both set iters"),
                           (["--executor", "ray", "--set", "render_threads=1"], "render on --cpus-per-run threads"),
                           (["--set", "lr.pose"], "expected name=value")):
        result = runner.invoke(app, ["sweep", "maryrose", *items, "--out", str(out)])
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2 and len(lines) == 1 and message in lines[0], (items, result.output)
    assert len(specs) == 1 and not out.exists()
