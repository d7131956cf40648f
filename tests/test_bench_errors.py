"""The benchmarks that take scene names answer a bad one as the CLI does: one line on stderr and exit code 2, before
any table line is printed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.parametrize("script", ["pose_recovery.py", "pose_optimum.py", "repair.py", "hull_noise.py",
                                    "reference_poses.py", "view_agreement.py", "hull_depths.py",
                                    "fitted_loss.py"])
def test_an_unknown_scene_is_one_error_line(script, tmp_path):
    more = [str(tmp_path / "out")] if script == "hull_depths.py" else []  # its second argument: the copy to write
    result = subprocess.run([sys.executable, str(BENCH / script), "nosuchscene", *more], capture_output=True,
                            text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "nosuchscene" in errors[0] and "Traceback" not in result.stderr
    assert result.stdout == "" and not (tmp_path / "out").exists()


@pytest.mark.parametrize("device, message", [("tpu", "--device must be cpu or cuda"),
                                             ("cuda", "--device cuda: no CUDA device is available")])
def test_rasterize_bench_bad_device_is_one_error_line(device, message, tmp_path):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device: the benchmark would run")
    result = subprocess.run([sys.executable, str(BENCH / "rasterize.py"), "--quick", "--device", device],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0] and "Traceback" not in result.stderr
    assert result.stdout == ""
