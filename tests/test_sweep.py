"""`warpbags sweep`'s own checks: settings it refuses are named in the sweep's terms, before any folder is made."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from warpbags.cli.main import app
from warpbags.errors import WarpbagsError
from warpbags.sweep import SweepSpec, run_sweep

runner = CliRunner()


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
