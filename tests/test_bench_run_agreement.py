"""`bench/run_agreement.py`: runs from one start, their errors and how far they disagree, as a table row and JSON."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "run_agreement.py"


def test_runs_from_one_start_are_compared_with_each_other_and_the_truth(tmp_path):
    out = tmp_path / "agreement.json"
    result = subprocess.run([sys.executable, str(BENCH), "synthetic-small", "--train-seeds", "0,1", "--set", "iters=6",
                             "--json", str(out)], capture_output=True, text=True, timeout=600, cwd=tmp_path,
                            env={**os.environ, "WARPBAGS_CACHE": str(tmp_path / "cache")})
    assert result.returncode == 0, result.stderr
    results = json.loads(out.read_text())
    [row] = results["rows"]
    assert len(row["error_per_run"]) == 2 and len(row["error_per_camera"]) == 4
    assert row["error"] == pytest.approx(sum(row["error_per_run"]) / 2)
    # the two seeds start from the same noisy poses (noise seed 0) and end apart: by at most the sum of their errors
    # (with Procrustes, up to its alignments' differences: 1.5x)
    assert row["agreement"]["pairs"] == [[0, 1]] and row["agreement"]["same_start"]
    assert 0 < row["disagreement"] < 1.5 * sum(row["error_per_run"])
    assert row["disagreement"] == pytest.approx(row["agreement"]["rotation_deg_mean"])
    assert any(line.startswith("synthetic-small") for line in result.stdout.splitlines())
    # the correlation line's numbers, per scene and view count: over the 4 cameras of the one noise seed
    assert results["noise_seeds"] == [0]
    [correlation] = results["correlations"]
    assert correlation["scene"] == "synthetic-small" and correlation["views"] == 4 and correlation["cameras"] == 4
    assert correlation["correlation"] == pytest.approx(
        np.corrcoef(row["error_per_camera"], row["disagreement_per_camera"])[0, 1])
    assert f"correlation {correlation['correlation']:.2f} over 4 cameras" in result.stdout
