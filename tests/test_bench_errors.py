"""The benchmarks answer bad input as the CLI does: one line on stderr and exit code 2, before any work and any
table line: a bad scene name, a bad number list, a bad or clashing `--set`."""

from __future__ import annotations

import runpy
import subprocess
import sys
from pathlib import Path

import pytest
import torch

BENCH = Path(__file__).resolve().parents[1] / "bench"


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
])
def test_bad_input_is_one_error_line_before_any_work(script, arguments, message, tmp_path, monkeypatch, capsys):
    """Checked before the scene is loaded (its name here is unknown too) and before any line of a table. Run in
    this process as `python bench/SCRIPT` runs it (`__main__`, its `clean_errors` entry point), which spares a
    process start per case; the test above starts each script as a process."""
    scene = [] if script in ("train_step.py", "rasterize.py") else ["nosuchscene"]
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), *scene, *arguments])
    monkeypatch.syspath_prepend(str(BENCH))
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()  # the scripts set torch's threads for their own process
    try:
        with pytest.raises(SystemExit) as exit_:
            runpy.run_path(str(BENCH / script), run_name="__main__")
    finally:
        torch.set_num_threads(threads)
    output = capsys.readouterr()
    assert exit_.value.code == 2, output.err
    errors = [line for line in output.err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0] and "Traceback" not in output.err, output.err
    assert output.out == ""


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
