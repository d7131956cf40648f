"""`bench/repair.py`: the repair stage against its controls from one coarse checkpoint, end to end at a tiny size."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench" / "repair.py"


def test_the_repair_benchmark_trains_its_controls_from_the_coarse_checkpoint(tmp_path):
    """The real-views control continues the coarse checkpoint with the pseudo-view ratio set to 0, a config the
    checkpoint's run did not have: it was refused as "config.json was changed after it started", after the coarse
    stage, the pairs, the fit and the repair iterations had run."""
    tiny = ["--set", "iters=6", "--set", "rounds=1", "--set", "hull_resolution=32", "--set", "init_points=300",
            "--set", "repair.loo_iters=8", "--set", "repair.loo_snapshot=4", "--set", "repair.loo_samples=1",
            "--set", "repair.fit_steps=2", "--set", "repair.pseudo_views=2"]
    result = subprocess.run([sys.executable, str(BENCH), "synthetic-small", "--repair-iters", "2", *tiny],
                            capture_output=True, text=True, timeout=600, cwd=tmp_path,
                            env={**os.environ, "WARPBAGS_CACHE": str(tmp_path / "cache")})
    assert result.returncode == 0, result.stdout + result.stderr
    rows = [line.split()[1] for line in result.stdout.splitlines() if line.startswith("synthetic-small")]
    assert rows == ["coarse", "real", "identity", "repair"]
