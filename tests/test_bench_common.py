"""bench/common.py: the settings merge, the `--set` checks and the JSON files the benchmarks
share."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import pytest

from warpbags.errors import WarpbagsError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from common import (add_training_options, check_options, merge_settings, pose_noise_checks,  # noqa: E402
                    resolution_check, training_overrides, write_json)


def test_merge_settings_merges_groups_field_by_field_and_leaves_its_inputs():
    base = {"views": 4, "repair": {"iters": 300, "fit_steps": 800}, "camera": {"precondition": False}}
    extra = {"views": 6, "repair": {"iters": 0}, "seed": 1}
    merged = merge_settings(base, extra)
    assert merged == {"views": 6, "repair": {"iters": 0, "fit_steps": 800}, "camera": {"precondition": False},
                      "seed": 1}
    assert base["repair"] == {"iters": 300, "fit_steps": 800} and base["views"] == 4


def _args(*settings: str, preset: str = "quick") -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_training_options(parser, "a TrainConfig field", json_help="also write here")
    return parser.parse_args(["--preset", preset, *(item for setting in settings for item in ("--set", setting))])


def test_training_overrides_parses_and_validates_the_settings():
    assert training_overrides(_args("lambda_chamfer=3", "repair.fit_steps=5")) == {
        "lambda_chamfer": 3, "repair": {"fit_steps": 5}}
    with pytest.raises(WarpbagsError, match="unknown training option"):
        training_overrides(_args("nosuchfield=1"))
    with pytest.raises(WarpbagsError, match="--preset"):
        training_overrides(_args(preset="nosuchpreset"))
    with pytest.raises(WarpbagsError) as error:  # the script's own settings of a run, checked too, and named
        training_overrides(_args("lambda_chamfer=3"), runs=[("fine", {"views": 4}),
                                                            ("the run of --views 1", {"views": 1})])
    assert str(error.value) == ("the run of --views 1 with --preset quick and --set {'lambda_chamfer': 3}: --views "
                                "must be >= 2, got 1")
    # a setting checked with the runs' own settings, not the preset's: 6 views per step is right for --views 6
    assert training_overrides(_args("views_per_step=6"), runs=[("--views 6", {"views": 6})]) == {"views_per_step": 6}


def test_training_overrides_refuses_a_field_the_script_sets_itself():
    fixed = {"views": "from --views", "repair.iters": "0: no repair stage"}
    with pytest.raises(WarpbagsError) as error:
        training_overrides(_args("views=4"), fixed)
    assert str(error.value) == "--set views: this benchmark sets views itself (from --views)"
    with pytest.raises(WarpbagsError, match="--set repair.iters:"):
        training_overrides(_args("repair.iters=5"), fixed)
    # other fields of the same group are the user's
    assert training_overrides(_args("repair.fit_steps=5"), fixed) == {"repair": {"fit_steps": 5}}


def test_write_json_writes_strict_json_with_nan_as_null(tmp_path):
    path = tmp_path / "tables" / "rows.json"
    write_json(path, {"rows": [{"psnr": math.nan, "rotation": 0.5, "seeds": (0, 1)}], "inf": math.inf})
    assert "NaN" not in path.read_text() and "Infinity" not in path.read_text()
    assert json.loads(path.read_text()) == {"rows": [{"psnr": None, "rotation": 0.5, "seeds": [0, 1]}], "inf": None}
    assert sorted(p.name for p in path.parent.iterdir()) == ["rows.json"]  # no temporary left beside it


def test_option_checks_pass_the_ends_of_their_ranges_and_raise_the_first_failure():
    check_options(pose_noise_checks(0.0, 0.0))
    check_options(pose_noise_checks(180.0, 4.0))  # the ends TrainConfig accepts for rot_noise_deg and trans_noise
    check_options([resolution_check(2), resolution_check(256)])
    with pytest.raises(WarpbagsError) as error:
        check_options(pose_noise_checks(math.nan, -1.0))  # the first failed check: the NaN rotation
    assert str(error.value) == "--rot must be in [0, 180] (a std in degrees), got nan"
    with pytest.raises(WarpbagsError, match=r"--trans must be in \[0, 4\]"):
        check_options(pose_noise_checks(5.0, 4.5))
    with pytest.raises(WarpbagsError, match=r"--resolution must be in \[2, 256\] \(voxels per axis\), got 257"):
        check_options([resolution_check(257)])
