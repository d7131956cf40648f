"""`warpbags sweep`'s own checks: settings it refuses are named in the sweep's terms, before any folder is made; the
eval.json of a finished run it reads is checked, and a metric held as null shows as n/a."""

from __future__ import annotations

import csv
import fcntl
import json
import math
import shutil

import pytest
import torch
from conftest import stopped_by_sigterm
from typer.testing import CliRunner

from warpbags.cli.main import app
from warpbags.data import SyntheticOptions, ensure_synthetic_scene
from warpbags.errors import WarpbagsError
from warpbags.files import finite_json, is_temporary
from warpbags.sweep import LocalExecutor, SweepSpec, combination_config, make_executor, run_sweep, sweep_runs

runner = CliRunner()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return ensure_synthetic_scene(SyntheticOptions(views=16, width=64, height=64),
                                  cache_dir=tmp_path_factory.mktemp("cache"))


def evaluation(psnr: float = 20.0, rot_final: float = 1.0, refine_iters: int = SweepSpec.refine_iters) -> dict:
    """The parts of an eval.json (`evaluate_run`, with the sweep's refinement iterations by default) that a sweep's
    row reads; each stage's and each row's numbers differ, so that a row that read the wrong one would show it."""
    poses = {stage: {"rotation_deg_mean": rotation, "translation_mean": translation}
             for stage, rotation, translation in (("initial", 5.0, 0.05), ("final", rot_final, 0.01))}
    images = {"mean": {"psnr": psnr, "ssim": 0.9, "flip": 0.1, "lpips": None}, "per_view": []}
    report = {"alignment": "procrustes", "poses": {"procrustes": poses}, "images": images}
    if refine_iters:
        report["images_after_test_pose_refinement"] = {
            "iters": refine_iters, "mean": {"psnr": psnr + 1.5, "ssim": 0.95, "flip": 0.05, "lpips": None},
            "per_view": []}
    return report


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
    # as many iterations as rounds pass this check (and go on to read the scene; rounds of one iteration move poses
    # only in a pose window of the whole round); so do the preset's own
    for overrides in ((("iters", 3), ("pose_round_window", (0.0, 1.0))), ()):
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


def test_the_tables_and_the_printed_table_hold_each_runs_values_in_their_columns(scene, tmp_path):
    """Nothing checked sweep.csv, the printed table's columns or a row's ssim and flip: a CSV without its first row, a
    table with rot init and final swapped or the refined PSNR under "PSNR", and rows with the refined SSIM and FLIP
    passed. sweep.csv holds sweep.json's rows; each printed row holds its run's values under their headers."""
    out = tmp_path / "sweep"
    values = {"baseline-4v-rot5-seed0": (20.0, 4.0), "bags-4v-rot5-seed0": (24.0, 0.5)}  # PSNR, final rotation error
    for run, (psnr, rot_final) in values.items():
        write_evaluation(out / run, evaluation(psnr=psnr, rot_final=rot_final))
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)],
                           env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    rows = json.loads((out / "sweep.json").read_text())
    assert [(row["run"], row["psnr"], row["psnr_refined"], row["rot_err_final"]) for row in rows] == [
        (run, psnr, psnr + 1.5, rot_final) for run, (psnr, rot_final) in values.items()]
    assert all((row["ssim"], row["flip"]) == (0.9, 0.1) for row in rows)  # unrefined, as the PSNR column is
    with open(out / "sweep.csv", newline="") as handle:
        assert list(csv.DictReader(handle)) == [{key: "" if value is None else str(value) for key, value in row.items()}
                                                for row in rows]
    header, *printed = [[cell.strip() for cell in line.split(bar)[1:-1]] for line in result.output.splitlines()
                        for bar in "┃│" if line.startswith(bar)]
    assert header == ["method", "views", "noise", "seed", "rot init", "rot final", "PSNR", "PSNR refined"]
    assert printed == [[row["method"], "4", "5", "0", "5.00", f"{row['rot_err_final']:.2f}", f"{row['psnr']:.2f}",
                        f"{row['psnr_refined']:.2f}"] for row in rows]


def test_the_curves_legend_tells_seeds_apart(scene, tmp_path, monkeypatch):
    """The curves of a sweep over two seeds had the same legend entry twice ("baseline, 4v, 5 deg"): with more than
    one seed, each names its seed."""
    import warpbags.report as report

    legends = {}
    save_figure = report._save_figure

    def saved(plt, figure, path):
        legends[path.name] = [text.get_text() for axis in figure.axes if axis.get_legend()
                              for text in axis.get_legend().get_texts()]
        save_figure(plt, figure, path)

    monkeypatch.setattr(report, "_save_figure", saved)
    out = tmp_path / "sweep"
    labels = []
    for seeds in ((0,), (0, 1)):
        spec = SweepSpec(scene=str(scene), out=out, rot_noises=(5,), views=(4,), seeds=seeds)
        for run in sweep_runs(spec):
            if not (out / run.name).exists():
                write_evaluation(out / run.name, evaluation())
                (out / run.name / "log.jsonl").write_text(
                    '{"iter": 1, "loss": 0.5, "rot_err_deg": 5.0, "trans_err": 0.1}\n')
        run_sweep(spec, log=lambda message: None)
        labels.append(legends["curves.png"])
    assert labels == [["baseline, 4v, 5 deg", "bags, 4v, 5 deg"],  # one seed: no need to name it
                      [f"{method}, 4v, 5 deg, seed {seed}" for seed in (0, 1) for method in ("baseline", "bags")]]


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

    out = tmp_path / "sweep"
    (out / "bags-4v-rot5-seed0").mkdir(parents=True)  # after baseline-4v-rot5-seed0, which is not done
    (out / "bags-4v-rot5-seed0" / "eval.json").write_text(content)
    _assert_refused_before_training(scene, out, monkeypatch, named)


def _assert_refused_before_training(scene, out, monkeypatch, named: str) -> None:
    """A sweep into `out` whose finished bags run's eval.json is unusable stops in one line naming it (`named`),
    before any run trains or any output is written."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"{out / 'bags-4v-rot5-seed0' / 'eval.json'}: {named}" in lines[0], lines[0]
    assert lines[0].endswith("remove it and run the sweep again to evaluate the run anew"), lines[0]
    assert sorted(path.name for path in out.iterdir()) == ["bags-4v-rot5-seed0"]


def pairwise_evaluation() -> dict:
    """`evaluation()` as `warpbags eval --pairwise` writes it for cameras that Procrustes fits: aligned pairwise."""
    report = evaluation()
    report["poses"]["pairwise"] = report["poses"]["procrustes"]
    return {**report, "alignment": "pairwise"}


@pytest.mark.parametrize("report, named", [
    (evaluation(refine_iters=100), "evaluated with 100 test pose refinement iterations, not the sweep's 50"),
    (evaluation(refine_iters=0), "evaluated with 0 test pose refinement iterations, not the sweep's 50"),
    (pairwise_evaluation(), "evaluated with the pairwise alignment, not the sweep's procrustes"),
])
def test_a_finished_run_evaluated_otherwise_than_the_sweep_is_one_line_before_anything_trains(scene, tmp_path,
                                                                                                monkeypatch, report,
                                                                                                named):
    """eval.json was read as it stood: a run evaluated again by `warpbags eval` (100 refinement iterations,
    --refine-iters 0, --pairwise) sat in the table beside the sweep's own evaluations, and its "PSNR refined" was the
    unrefined PSNR when it had no refinement. It is refused, naming the file, before any run trains; evaluating it
    again is the user's to ask (the sweep does not overwrite an evaluation someone made on purpose)."""
    out = tmp_path / "sweep"
    write_evaluation(out / "bags-4v-rot5-seed0", report)  # after baseline-4v-rot5-seed0, which is not done
    _assert_refused_before_training(scene, out, monkeypatch, named)


def test_a_sweep_without_refinement_has_no_refined_psnr_and_two_views_align_pairwise(scene, tmp_path):
    """psnr_refined of a sweep that does not refine the test poses was the unrefined PSNR. It is None; and a run of
    two views, which Procrustes cannot align (eval.json holds its pairwise pose errors alone), is the sweep's own."""
    out = tmp_path / "sweep"
    two_views = evaluation(refine_iters=0)
    two_views["poses"]["pairwise"] = two_views["poses"].pop("procrustes")
    for run in ("baseline-2v-rot5-seed0", "bags-2v-rot5-seed0"):
        write_evaluation(out / run, {**two_views, "alignment": "pairwise"})
    rows = run_sweep(SweepSpec(scene=str(scene), out=out, rot_noises=(5,), views=(2,), refine_iters=0),
                     log=lambda message: None)
    assert [(row["psnr"], row["psnr_refined"], row["rot_err_final"]) for row in rows] == [(20.0, None, 1.0)] * 2


def test_a_damaged_log_of_a_finished_run_is_one_line_before_anything_trains(scene, tmp_path, monkeypatch):
    """The curves plot reads each run's log.jsonl: a damaged line in a finished run's log stopped the sweep after every
    new run had trained and sweep.csv and sweep.json had been rewritten, before the plots. It is one line naming the
    line, before any run trains, and the sweep writes nothing."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    out = tmp_path / "sweep"
    done = out / "bags-4v-rot5-seed0"  # after baseline-4v-rot5-seed0, which is not done
    write_evaluation(done, evaluation())
    (done / "log.jsonl").write_text('{"iter": 1, "loss": 0.5, "rot_err_deg": 5.0, "trans_err": 0.1}\n{"iter": 2, "lo\n')
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"{done / 'log.jsonl'}:2: not a log record" in lines[0], lines[0]
    assert sorted(path.name for path in out.iterdir()) == ["bags-4v-rot5-seed0"]


def test_a_second_sweep_into_a_folder_is_one_line_while_the_first_runs(scene, tmp_path, monkeypatch):
    """Two sweeps into one folder at once both trained the same runs (one clearing the other's unfinished start, or
    both resuming one run into one log). A sweep holds a lock on its folder from before it reads it to after its
    plots and tables, with either executor (the driver holds it); a second sweep is one line before it reads or
    writes anything, and the lock file is gone when the sweep ends."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    out = tmp_path / "sweep"
    out.mkdir()
    with open(out / ".sweep.lock", "a") as held:  # as a running sweep holds it
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0].endswith(f"another sweep is running in {out}"), lines[0]
    assert sorted(path.name for path in out.iterdir()) == [".sweep.lock"]  # the running sweep's, left to it

    for run in ("baseline-4v-rot5-seed0", "bags-4v-rot5-seed0"):
        write_evaluation(out / run, evaluation())
    spec = SweepSpec(scene=str(scene), out=out, rot_noises=(5,), views=(4,))
    refused = []

    class SecondSweepMeanwhile(LocalExecutor):
        """Starts a second sweep into the folder while the runs run."""

        def map(self, spec, runs, scene, log):
            with pytest.raises(WarpbagsError) as error:
                run_sweep(spec, log=log)
            refused.append(str(error.value))
            return super().map(spec, runs, scene, log)

    assert len(run_sweep(spec, log=lambda message: None, executor=SecondSweepMeanwhile())) == 2
    assert refused == [f"another sweep is running in {out}"]
    assert sorted(path.name for path in out.iterdir()) == sorted(["baseline-4v-rot5-seed0", "bags-4v-rot5-seed0",
                                                                  "sweep.json", "sweep.csv", "curves.png",
                                                                  "psnr_vs_noise.png", "pose_error_vs_noise.png"])


def test_set_resolution_reads_the_scene_at_that_resolution(scene, tmp_path, monkeypatch):
    """`--set resolution=2` was recorded in each run's config.json while the runs trained on the scene at its
    default resolution. They train on it at the resolution given, as `warpbags train --resolution` does."""
    trained = []

    class Stop(Exception):
        """Raised where the run would train: the scene it was given is what this test reads."""

    def start_or_resume(scene, config, *args, **kwargs):
        trained.append((scene.resolution, scene.width, config.resolution))
        raise Stop

    monkeypatch.setattr("warpbags.sweep.start_or_resume", start_or_resume)
    for resolution, width in ((None, 64), (2, 32)):
        overrides = () if resolution is None else (("resolution", resolution),)
        with pytest.raises(Stop):
            run_sweep(SweepSpec(scene=str(scene), out=tmp_path / f"sweep{resolution}", rot_noises=(5,), views=(4,),
                                overrides=overrides), log=lambda message: None)
        assert trained.pop() == (resolution or 1, width, resolution)


def test_an_earlier_run_with_another_group_field_names_that_field(scene, tmp_path, monkeypatch):
    """A sweep over the runs of an earlier one with another `--set lr.pose` named the whole group: "lr=LearningRates(
    ...twelve fields...), not LearningRates(...)". It names the field as --set spells it."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    out = tmp_path / "sweep"
    earlier = SweepSpec(scene=str(scene), out=out, rot_noises=(5,), views=(4,), overrides=(("lr", {"pose": 0.01}),))
    run = sweep_runs(earlier)[0]
    (out / run.name).mkdir(parents=True)  # a run of the earlier sweep, stopped before its first checkpoint
    (out / run.name / "config.json").write_text(json.dumps({"config": combination_config(earlier, run).to_dict(),
                                                            "scene_root": str(scene.resolve())}))
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--set", "lr.pose=0.005",
                                 "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"{out / run.name} holds a run with lr.pose=0.01, not 0.005: choose another --out" in lines[0], lines[0]


@pytest.mark.parametrize("finished", [False, True])
def test_an_earlier_run_holding_retired_settings_is_refused(scene, tmp_path, monkeypatch, finished):
    """A config.json of a reverted experiment's version (camera.restarts=3) reads back without it: a finished run was
    skipped as done and its row joined the table as if of this sweep's settings."""

    def train(*args, **kwargs):
        raise AssertionError("a run trained")

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    out = tmp_path / "sweep"
    spec = SweepSpec(scene=str(scene), out=out, rot_noises=(5,), views=(4,))
    run = sweep_runs(spec)[0]
    (out / run.name).mkdir(parents=True)
    config = combination_config(spec, run).to_dict()
    config["camera"]["restarts"] = 3
    (out / run.name / "config.json").write_text(json.dumps({"config": config, "scene_root": str(scene.resolve())}))
    if finished:
        (out / run.name / "eval.json").write_text("{}")
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0] == (f"error: sweep run {run.name}: {out / run.name} holds a run with camera.restarts, settings of "
                        "an earlier warpbags that this one has no more: choose another --out (or remove that run)")


def test_a_sweep_says_where_its_views_fix_procrustes_weakly(scene, tmp_path, monkeypatch):
    """The runs' evaluation is quiet: where the training cameras lie nearly on a line, the sweep says so itself, once
    per view count, before anything trains (its tables hold Procrustes' errors)."""

    class Stop(Exception):
        pass

    def train(*args, **kwargs):
        raise Stop

    asked = []

    def weak(viewmats):
        asked.append(len(viewmats))
        return "the camera centres spread 0.05 as far across their main line as along it" if len(asked) == 1 else None

    monkeypatch.setattr("warpbags.sweep.start_or_resume", train)
    monkeypatch.setattr("warpbags.sweep.procrustes_weak", weak)
    lines = []
    with pytest.raises(Stop):
        run_sweep(SweepSpec(scene=str(scene), out=tmp_path / "sweep", rot_noises=(5,), views=(4, 6)), log=lines.append)
    assert asked == [4, 6]
    assert lines[0] == ("4 views: the camera centres spread 0.05 as far across their main line as along it; the "
                        "tables' pose errors are Procrustes' (eval.json holds pairwise ones)"), lines
    assert not any(line.startswith("6 views") for line in lines)


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
    (".sweep.lock/", ".sweep.lock is a folder, not a file to lock the sweep's folder"),
])
def test_a_folder_in_the_way_of_a_run_or_the_tables_is_one_line_before_anything_trains(scene, tmp_path, monkeypatch,
                                                                                        blocker, named):
    """A run's folder holding other files was refused when its turn came, after the runs before it had trained; a
    folder named as a table or figure was a traceback after every run. Both are one line before any run trains, and
    so is a folder named as the sweep's lock file."""

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


def test_a_gpu_count_that_is_not_a_finite_number_is_named_before_ray_starts():
    """--gpus-per-run nan passed the `< 0` check and failed in Ray's scheduling after it had started."""
    from warpbags.sweep import RayExecutor

    for gpus in (math.nan, math.inf, -1.0):
        with pytest.raises(WarpbagsError, match="--gpus-per-run must be a finite number >= 0"):
            RayExecutor(cpus_per_run=1, gpus_per_run=gpus)


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


def test_a_local_sweep_stopped_by_sigterm_leaves_its_runs_resumable_and_no_lock(scene, tmp_path):
    """`kill` ended a local sweep at once, leaving `.sweep.lock` and, outside a run's training, a run folder holding
    only its start's claim. It now stops as on Ctrl-C: exit 143, the lock gone, and the training run takes the signal
    itself (the handler the sweep set is no one else's): it finishes its iteration and saves a checkpoint."""
    out = tmp_path / "sweep"
    first_run = out / "baseline-4v-rot5-seed0"

    def checkpoints() -> list[int]:  # not a checkpoint's `atomic_output` temporary (checkpoint_000100.tmp.pt)
        return sorted(int(path.stem.removeprefix("checkpoint_")) for path in first_run.glob("**/checkpoint_*.pt")
                      if not is_temporary(path))

    code, output = stopped_by_sigterm(["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--iters", "400",
                                       "--out", str(out)], ready=lambda: bool(checkpoints()))
    assert code == 143 and "stopped by SIGTERM" in output, output
    assert not (out / ".sweep.lock").exists()
    assert checkpoints()[-1] % 100 != 0, checkpoints()  # the quick preset checkpoints every 100: one of the stop's
    assert not (first_run / ".starting").exists()


@pytest.fixture
def sweep_line(tmp_path, monkeypatch):
    """`sweep_line(*arguments)`: the one line of `warpbags sweep *arguments` into a new folder, which the sweep must
    not have made; a sweep that passes its checks stops at reading its scene ("the scene was read"), trains nothing."""

    def scene_read(*args, **kwargs):
        raise WarpbagsError("the scene was read")

    monkeypatch.setattr("warpbags.sweep.open_scene", scene_read)

    def line(*arguments: str) -> str:
        out = tmp_path / "s"
        result = runner.invoke(app, ["sweep", *arguments, "--out", str(out)])
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2 and len(lines) == 1 and "Traceback" not in result.output, result.output
        assert not out.exists()
        return lines[0]

    return line


@pytest.mark.parametrize("arguments, message", [
    (["--preset", "paper", "--iters", "20", "--repair-iters", "0"],
     "pose optimization starts at iteration 1000 (pose_opt_start), after every iteration of their pose windows; "
     "give more --iters, or a smaller --set pose_opt_start=N"),
    (["--iters", "3"], "3 iterations in 3 round(s) leave no iteration in any round's pose window (0.25, 1.0) (shares "
                       "of a round); give more --iters"),
])
def test_bags_runs_whose_schedule_never_moves_a_pose_are_refused(sweep_line, arguments, message):
    """The trainer warns at its start that poses will not move (the paper preset's poses start at iteration 1000;
    quick's rounds of one iteration hold no iteration of their pose window), but a sweep's runs log nothing: its
    "bags" rows were trained with fixed poses. Such a sweep is refused in one line before anything is made, and the
    same sweep with iterations enough for its poses to move goes on (to read its scene)."""
    common = ["maryrose", "--rot-noises", "10", "--views", "4", "--refine-iters", "0"]
    line = sweep_line(*common, *arguments)
    assert line == f"error: sweep run bags-4v-rot10-seed0: the bags runs would never move a pose: {message}"
    moving = ["--set", "pose_opt_start=19"] if "paper" in arguments else ["--set", "pose_round_window=[0, 1]"]
    assert sweep_line(*common, *arguments, *moving) == "error: the scene was read"


def test_a_repairer_with_the_repair_stage_off_is_refused_as_train_refuses_it(sweep_line):
    """`warpbags train --repairer X` without repair iterations is refused; a sweep's `--set repair.repairer=X`
    trained without its repairer, silently. It is one line, and with --repair-iters the sweep goes on."""
    line = sweep_line("maryrose", "--set", "repair.repairer=foo")
    assert line.endswith("--set repair.repairer foo would be unused: the repair stage is off (repair.iters is 0); add "
                         "--repair-iters N"), line
    assert sweep_line("maryrose", "--set", "repair.repairer=unet", "--repair-iters", "2") == "error: the scene was read"


def test_seeds_that_torch_would_take_as_another_seed_are_refused(sweep_line):
    """torch's CPU generator keeps a seed modulo 2^32: `--seeds 0,4294967296` trained and reported one run twice. The
    message names the sweep's --seeds (it named train's --seed, which the sweep has not)."""
    assert sweep_line("maryrose", "--seeds", "0,4294967296") == (
        "error: --seeds '0,4294967296': 4294967296 is above 4294967295")
    assert sweep_line("maryrose", "--seeds=-1") == "error: --seeds '-1': -1 is below 0"
    assert sweep_line("maryrose", "--seeds", "0,4294967295") == "error: the scene was read"


@pytest.mark.parametrize("scene, root, message", [
    ("maryrose", "root", "--data-root is read only by the presets ethiopianhead, kitchen, moldgoldcape, not by scene "
                         "'maryrose': leave it out"),
    ("kitchen", "missing", "--data-root {root}: not a folder"),
    ("kitchen", "root", "the scene was read"),
])
def test_a_data_root_the_scene_does_not_read_is_refused(sweep_line, tmp_path, scene, root, message):
    """`--data-root` was ignored, silently, for every scene but the data-root presets, even a folder that does not
    exist (`warpbags train` checks it through the same helper: tests/test_cli_options.py)."""
    (tmp_path / "root").mkdir()
    assert sweep_line(scene, "--data-root", str(tmp_path / root)) == f"error: {message.format(root=tmp_path / root)}"
