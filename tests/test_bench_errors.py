"""The benchmarks answer bad input as the CLI does: one line on stderr and exit code 2, before any work and any
table line: a bad scene name, a bad number list, a bad or clashing `--set`, an option out of its range, a --keep
holding an earlier run. A failure of bench/train_step.py's configuration processes or of OpenSplat is one line too."""

from __future__ import annotations

import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from warpbags.errors import WarpbagsError

BENCH = Path(__file__).resolve().parents[1] / "bench"
# Options that keep a run short where the check under test is missing (the benchmark then runs instead of failing)
QUICK_RASTERIZE = ["--quick", "--gaussians", "100", "--cameras", "1", "--repeats", "1"]
QUICK_TRAIN_STEP = ["--inits", "random", "--points", "100", "--steps", "1", "--warmup", "0"]


@pytest.mark.parametrize("script", ["pose_recovery.py", "pose_optimum.py", "repair.py", "hull_noise.py",
                                    "reference_poses.py", "view_agreement.py", "hull_depths.py",
                                    "fitted_loss.py", "view_matches.py", "run_agreement.py"])
def test_an_unknown_scene_is_one_error_line(script, tmp_path):
    more = [str(tmp_path / "out")] if script == "hull_depths.py" else []  # its second argument: the copy to write
    result = subprocess.run([sys.executable, str(BENCH / script), "nosuchscene", *more], capture_output=True,
                            text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "nosuchscene" in errors[0] and "Traceback" not in result.stderr
    assert result.stdout == "" and not (tmp_path / "out").exists()


@pytest.mark.parametrize("script, arguments, message", [
    ("pose_optimum.py", ["--start-noise", "5"], "--start-noise '5': '5' is not ROT_DEG/TRANS"),
    ("pose_optimum.py", ["--start-noise", ","], "--start-noise ','"),
    ("pose_optimum.py", ["--set", "views=4"], "--set views: this benchmark sets views itself"),
    ("pose_optimum.py", ["--set", "camera.centroid_start=true"], "--set camera.centroid_start:"),
    ("repair.py", ["--set", "views=4"], "--set views: this benchmark sets views itself (from --views)"),
    ("repair.py", ["--set", "rot_noise_deg=5"], "--set rot_noise_deg:"),
    ("repair.py", ["--set", "trans_noise=0.1"], "--set trans_noise:"),
    ("repair.py", ["--set", "nosuchfield=1"], "nosuchfield"),
    ("pose_recovery.py", ["--rot", "a"], "--rot 'a': 'a' is not a number"),
    ("pose_recovery.py", ["--seeds", ","], "--seeds ','"),
    ("pose_recovery.py", ["--set", "seed=1"], "--set seed:"),
    ("pose_recovery.py", ["--set", "camera.fix_first_camera=true"], "--set camera.fix_first_camera: this benchmark"),
    ("pose_recovery.py", ["--set", "rot_noise_fixed=true"], "--set rot_noise_fixed: this benchmark"),
    ("fitted_loss.py", ["--seeds", ","], "--seeds ','"),
    ("run_agreement.py", ["--train-seeds", "3,3"], "--train-seeds '3,3': give two different seeds or more"),
    ("run_agreement.py", ["--train-seeds", "0,0,1"], "--train-seeds '0,0,1': give two different seeds or more, each"),
    ("run_agreement.py", ["--noise-seeds", "2,2"], "--noise-seeds '2,2': a seed given twice"),
    ("run_agreement.py", ["--rot", "0", "--trans", "0"], "without noise the scene's poses are no truth"),
    ("run_agreement.py", ["--views", "1"], "--views '1': 1 is below 2"),
    ("run_agreement.py", ["--set", "seed=1"], "--set seed: this benchmark sets seed itself (from --train-seeds)"),
    ("fitted_loss.py", ["--set", "views=6"], "--set views:"),
    ("view_agreement.py", ["--sizes", "128,big"], "--sizes '128,big': 'big' is not an integer"),
    ("view_agreement.py", ["--set", "max_image_size=64"], "--set max_image_size:"),
    ("view_matches.py", ["--views", "4,1"], "--views 4,1: at least 2 views make a pair"),
    ("view_matches.py", ["--ratio", "1.5"], "--ratio must be in (0, 1], got 1.5"),
    ("view_matches.py", ["--min-inliers", "7"], "--min-inliers must be at least 8, got 7"),
    ("train_step.py", ["--views", ","], "--views ','"),
    ("train_step.py", ["--opensplat", "opensplat", "--sh-degree", "2"], "--opensplat runs OpenSplat at SH degree 0"),
    ("rasterize.py", ["--repeats", "0"], "--repeats must be >= 1, got 0"),  # was a StatisticsError traceback
    ("train_step.py", ["--inits", "sphere"], "--inits 'sphere'"),
    ("train_step.py", ["--device", "cuda", "--pixel-blocks", "1x1"],
     "not with --device cuda" if torch.cuda.is_available() else "--device cuda: no CUDA device is available"),
    # pose noise in the scripts' own option names, before the header (was: after the first row, as --rot-noise-deg)
    ("pose_recovery.py", ["--rot", "0,-5", "--start-only"], "--rot must be in [0, 180] (a std in degrees), got -5"),
    ("pose_recovery.py", ["--trans", "-0.1"], "--trans must be in [0, 4]"),
    ("run_agreement.py", ["--rot", "nan"], "--rot must be in [0, 180] (a std in degrees), got nan"),
    ("run_agreement.py", ["--trans", "5"], "--trans must be in [0, 4] (a std in scene units"),
    ("fitted_loss.py", ["--rot", "181"], "--rot must be in [0, 180]"),
    ("fitted_loss.py", ["--trans", "-1"], "--trans must be in [0, 4]"),
    # the errors are after Procrustes alignment of 3 camera centres or more (was: a traceback once a run had run)
    ("pose_recovery.py", ["--views", "4,2"],
     "--views '4,2': sim(3) Procrustes alignment needs 3 cameras or more, got 2"),
    ("fitted_loss.py", ["--views", "2"], "--views 2: sim(3) Procrustes alignment needs 3 cameras or more"),
    # a variant whose settings clash with --set, named (was: after the runs before it, naming `warpbags train`'s
    # --camera-param)
    ("pose_recovery.py", ["--variants", "bags,frozen-orbit", "--set", "camera.parameterization=camera"],
     "--variants frozen-orbit: its settings {'camera': {'orbit_from_round': 99}} with --preset quick and --set "
     "{'camera': {'parameterization': 'camera'}}: camera.orbit_from_round needs the object parameterization"),
    ("repair.py", ["--rot", "-1"], "--rot must be in [0, 180]"),
    # no repair iterations: four models trained, then no repair stage to measure
    ("repair.py", ["--repair-iters", "0"], "--repair-iters must be >= 1 (this benchmark measures the repair stage)"),
    ("repair.py", ["--set", "repair.iters=0"], "--set repair.iters must be >= 1"),
    # bad numbers that were a traceback, or a row of zeros
    ("hull_noise.py", ["--resolution", "0"], "--resolution must be in [2, 256] (voxels per axis), got 0"),
    ("hull_noise.py", ["--resolution", "-3"], "--resolution must be in [2, 256] (voxels per axis), got -3"),
    ("hull_depths.py", ["out", "--resolution", "0"], "--resolution must be in [2, 256] (voxels per axis), got 0"),
    ("run_steps.py", ["--iteration", "-5"], "--iteration must be >= 0, got -5"),
    ("pose_optimum.py", ["--pose-lr", "nan"], "--pose-lr must be a positive number, got nan"),
    ("pose_optimum.py", ["--views", "2"], "--views 2: sim(3) Procrustes alignment needs 3 cameras or more"),
    ("view_agreement.py", ["--refine-iters", "-1"], "--refine-iters must be >= 1, got -1"),
    ("rasterize.py", ["--tile-size", "0", *QUICK_RASTERIZE], "--tile-size must be >= 1 (pixels), got 0"),
    # a pixel block the rasterizer would shrink (each side to a power of two dividing the tile): the columns would
    # be labelled with a block that did not run
    ("rasterize.py", ["--blocks", "3x3,8x8", *QUICK_RASTERIZE],
     "--blocks 3x3: the rasterizer would run it as 2x2 on 4 px tiles"),
    ("rasterize.py", ["--blocks", "1x1,8x8", *QUICK_RASTERIZE],
     "--blocks 8x8: the rasterizer would run it as 4x4 on 4 px tiles"),
    ("rasterize.py", ["--tile-size", "16", "--blocks", "8x8", *QUICK_RASTERIZE],
     "--blocks 8x8: pixel block 8x8: the rasterizer is built for"),
    ("train_step.py", ["--pixel-blocks", "1x1,3x3", *QUICK_TRAIN_STEP],
     "--pixel-blocks '1x1,3x3': the rasterizer would run 3x3 as 2x2 on its 4 px tiles"),
    ("train_step.py", ["--pixel-blocks", "8x8", *QUICK_TRAIN_STEP], "would run 8x8 as 4x4"),
    # maryrose trains on 4 views: a step of 8 renders those 4 (was: a column labelled 8v)
    ("train_step.py", ["--views", "1,8", *QUICK_TRAIN_STEP],
     "--views '1,8': a step renders at most maryrose's 4 training views, not 8"),
    ("train_step.py", ["--views", "0", *QUICK_TRAIN_STEP], "--views '0': 0 is below 1"),  # was a ZeroDivisionError
    ("train_step.py", ["--sh-degree", "9", *QUICK_TRAIN_STEP], "--sh-degree must be 0-3, got 9"),
    # OpenSplat's binary checked before the first configuration, not run after the last
    ("train_step.py", ["--opensplat", "nosuch/opensplat", *QUICK_TRAIN_STEP],
     "--opensplat nosuch/opensplat: not an executable file"),
    ("train_step.py", ["--opensplat", ".", *QUICK_TRAIN_STEP], "--opensplat .: not an executable file"),
])
def test_bad_input_is_one_error_line_before_any_work(script, arguments, message, tmp_path, monkeypatch, capsys):
    """Checked before the scene is loaded (its name here is unknown too) and before any line of a table. Run in
    this process as `python bench/SCRIPT` runs it (`__main__`, its `clean_errors` entry point), which spares a
    process start per case; the test above starts each script as a process."""
    scene = [] if script in ("train_step.py", "rasterize.py") else ["nosuchscene"]
    code, output = _run_in_process(script, [*scene, *arguments], tmp_path, monkeypatch, capsys)
    assert code == 2, output.err
    errors = [line for line in output.err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0] and "Traceback" not in output.err, output.err
    assert output.out == ""


@pytest.mark.parametrize("script", ["pose_recovery.py", "pose_optimum.py", "repair.py"])
def test_a_setting_is_checked_with_the_runs_own_view_count(script, tmp_path, monkeypatch, capsys):
    """`--views 6 --set views_per_step=6` is right for the runs the script trains: it was refused as over the
    preset's 4 views (the scene's own error comes first now: its name here is unknown)."""
    code, output = _run_in_process(script, ["nosuchscene", "--views", "6", "--set", "views_per_step=6"], tmp_path,
                                   monkeypatch, capsys)
    errors = [line for line in output.err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and "nosuchscene" in errors[0], output.err


@pytest.mark.parametrize("script", ["pose_recovery.py", "fitted_loss.py", "run_agreement.py", "pose_optimum.py",
                                    "view_agreement.py", "view_matches.py", "reference_poses.py", "train_step.py"])
def test_a_json_path_that_cannot_be_written_fails_before_any_work(script, tmp_path, monkeypatch, capsys):
    """A folder where --json should go: one line before the scene is loaded (its name here is unknown too), not an
    OSError at the first write, after the first row's runs (train_step.py: after every configuration)."""
    (tmp_path / "rows.json").mkdir()
    arguments = QUICK_TRAIN_STEP if script == "train_step.py" else ["nosuchscene"]
    code, output = _run_in_process(script, [*arguments, "--json", "rows.json"], tmp_path, monkeypatch, capsys)
    assert code == 2 and "Traceback" not in output.err and output.out == "", output.err
    assert output.err == "error: rows.json is a folder, not a file for --json\n"


@pytest.fixture(scope="module")
def scene_cache(tmp_path_factory):
    """A cache folder holding synthetic-small, generated once for the tests that load it."""
    folder = tmp_path_factory.mktemp("cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("WARPBAGS_CACHE", str(folder))
        patch.syspath_prepend(str(BENCH))
        from common import open_bench_scene  # noqa: PLC0415 - bench/ is on the path for this fixture only

        open_bench_scene("synthetic-small")
    return folder


@pytest.mark.parametrize("script, arguments, message", [
    # a view count the scene lacks: before the first run (was: when its run started, after those of 4 views)
    ("pose_recovery.py", ["--views", "4,17", "--seeds", "0", "--start-only"],
     "scene synthetic-small has 16 images, fewer than --views 17"),
    ("run_agreement.py", ["--views", "4,17", "--train-seeds", "0,1", "--set", "iters=6"],
     "scene synthetic-small has 16 images, fewer than --views 17"),
    ("fitted_loss.py", ["--views", "17", "--seeds", "0", "--fit-seeds", "0", "--set", "iters=6"],
     "scene synthetic-small has 16 images, fewer than --views 17"),
    ("pose_optimum.py", ["--views", "17", "--fit-iters", "2", "--pose-iters", "1"],
     "scene synthetic-small has 16 images, fewer than --views 17"),
    # a folder as --json (was: an error after the first row)
    ("pose_recovery.py", ["--seeds", "0", "--start-only", "--json", "."], ". is a folder, not a file for --json"),
])
def test_bad_input_on_a_scene_that_loads_fails_before_the_first_row(script, arguments, message, scene_cache,
                                                                     tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WARPBAGS_CACHE", str(scene_cache))
    code, output = _run_in_process(script, ["synthetic-small", *arguments], tmp_path, monkeypatch, capsys)
    assert code == 2 and "Traceback" not in output.err and output.out == "", (output.out, output.err)
    assert output.err == f"error: {message}\n"


def test_repair_refuses_a_keep_folder_that_holds_an_earlier_run(tmp_path, monkeypatch, capsys):
    """A second run into the same --keep would reuse the first's repair pairs and copy its repaired checkpoint as
    its own coarse one: refused before the scene is loaded. Another scene's runs there are no obstacle (the scene,
    unknown, is then the error)."""
    (tmp_path / "kept" / "nosuchscene-4v-repair" / "repair").mkdir(parents=True)
    code, output = _run_in_process("repair.py", ["nosuchscene", "--keep", "kept"], tmp_path, monkeypatch, capsys)
    assert code == 2 and "Traceback" not in output.err and output.out == ""
    assert output.err.startswith("error: --keep kept: kept/nosuchscene-4v-repair exists"), output.err
    code, output = _run_in_process("repair.py", ["otherscene", "--keep", "kept"], tmp_path, monkeypatch, capsys)
    assert code == 2 and "--keep" not in output.err and "otherscene" in output.err, output.err


def test_train_step_child_failure_is_one_error_line(tmp_path, monkeypatch, capsys):
    """A configuration's process that fails (its traceback on stderr) is one line naming the configuration and the
    child's error, not a RuntimeError holding the child's traceback."""
    run = subprocess.run

    def failing_child(command, *args, **kwargs):
        if str(command[1]).endswith("train_step.py"):
            return subprocess.CompletedProcess(command, 1, "", "Traceback (most recent call last):\n  File ...\n"
                                               "warpbags.errors.WarpbagsError: sh_degree must be 0-3, got 4\n")
        return run(command, *args, **kwargs)

    monkeypatch.setattr(subprocess, "run", failing_child)
    code, output = _run_in_process("train_step.py", ["--inits", "random", "--views", "1"], tmp_path, monkeypatch,
                                   capsys)
    assert code == 2 and "Traceback" not in output.err and output.out == "", output.err
    assert output.err.startswith("error: the configuration --one random 1 ") and output.err.endswith(
        "failed: warpbags.errors.WarpbagsError: sh_degree must be 0-3, got 4\n"), output.err


def test_opensplat_that_runs_no_steps_is_one_error_line(monkeypatch):
    """An OpenSplat that exits without its "Step N:" lines (here `true`) is a WarpbagsError naming the binary, not a
    RuntimeError."""
    monkeypatch.syspath_prepend(str(BENCH))
    import train_step  # noqa: PLC0415 - bench/ is on the path for this test only

    monkeypatch.setattr(train_step, "write_opensplat_project", lambda folder, points: {})  # no scene to write
    binary = Path(shutil.which("true"))
    with pytest.raises(WarpbagsError) as error:
        train_step.run_opensplat(binary, points=10, steps=2, warmup=1)
    assert str(error.value) == (f"--opensplat {binary}: exited with code 0 after 0 \"Step N:\" lines, needed 3 or "
                                "more; its last line: (none)")


def _run_in_process(script: str, arguments: list[str], tmp_path, monkeypatch, capsys):
    """Run `python bench/SCRIPT ARGUMENTS` in this process (`__main__`, its `clean_errors` entry point) in
    `tmp_path`: its exit code and captured output."""
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), *arguments])
    monkeypatch.syspath_prepend(str(BENCH))
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()  # the scripts set torch's threads for their own process
    try:
        with pytest.raises(SystemExit) as exit_:
            runpy.run_path(str(BENCH / script), run_name="__main__")
    finally:
        torch.set_num_threads(threads)
    return exit_.value.code, capsys.readouterr()


@pytest.mark.parametrize("script, arguments", [("rasterize.py", ["--quick"]), ("train_step.py", [])])
@pytest.mark.parametrize("device, message", [("tpu", "--device must be cpu or cuda"),
                                             ("cuda", "--device cuda: no CUDA device is available")])
def test_speed_bench_bad_device_is_one_error_line(script, arguments, device, message, tmp_path):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device: the benchmark would run")
    result = subprocess.run([sys.executable, str(BENCH / script), *arguments, "--device", device],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0] and "Traceback" not in result.stderr
    assert result.stdout == ""
