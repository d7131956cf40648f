"""`bench/pose_recovery.py --start-only`: the poses training would start from, without training, as a table row and
in the JSON."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench" / "pose_recovery.py"


def test_start_only_reports_the_silhouettes_start_without_training(tmp_path):
    out = tmp_path / "start.json"
    result = subprocess.run([sys.executable, str(BENCH), "synthetic-small", "--seeds", "0", "--start-only",
                             "--variants", "bags,truth-start", "--rot", "15,20", "--json", str(out)], capture_output=True, text=True,
                            timeout=600, cwd=tmp_path, env={**os.environ, "WARPBAGS_CACHE": str(tmp_path / "cache")})
    assert result.returncode == 0, result.stderr
    row, truth_start, row_20 = json.loads(out.read_text())["rows"]
    assert row_20["variant"] == "bags" and row_20["rot_noise"] == 20.0  # truth-start once, not once per --rot
    # each row names the noise its runs had: the truth-start variant has none, whatever --rot says
    assert (row["rot_noise"], row["trans_noise"]) == (15.0, 0.3)
    assert (truth_start["rot_noise"], truth_start["trans_noise"]) == (0.0, 0.0) and truth_start["rot_init"] < 1e-3
    assert any(line.split()[2:4] == ["0/0", "truth-start"] for line in result.stdout.splitlines())
    # The mask-centroid start and the coherence solve bring 15-deg cameras in before any Gaussian is fitted (measured:
    # 14.17 -> 8.03 deg on this scene and seed); nothing was trained, so there is no end error to report.
    assert row["rot_start"] < 0.75 * row["rot_init"]
    assert row["rot_start_per_seed"] == [row["rot_start"]]
    assert "rot_mean" not in row and "minutes" not in row["runs"][0]
    assert any(line.startswith("synthetic-small") for line in result.stdout.splitlines())
