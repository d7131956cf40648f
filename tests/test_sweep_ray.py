"""`warpbags sweep --executor ray`: runs as Ray tasks on a local Ray instance give the local executor's results
and resume alike; bad executor options are one line."""

from __future__ import annotations

import json
import os
import signal
import sys

import pytest
from typer.testing import CliRunner

from warpbags.cli.main import app
from warpbags.data import SyntheticOptions, ensure_synthetic_scene
from warpbags.sweep import RayExecutor, SweepSpec, run_sweep

if os.environ.get("CI") == "true":  # CI installs the ray extra (scripts/setup.sh): missing is a failure there
    import ray
else:
    ray = pytest.importorskip("ray", reason="needs the ray extra: pip install warpbags[ray]")

runner = CliRunner()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return ensure_synthetic_scene(SyntheticOptions(views=16, width=64, height=64),
                                  cache_dir=tmp_path_factory.mktemp("cache"))


@pytest.fixture
def local_ray(monkeypatch):
    """A local Ray instance with this machine's two cores, no dashboard and no usage report; stopped after."""
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    previous = signal.getsignal(signal.SIGTERM)
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()
    # Ray's core worker leaves its SIGTERM handler (it exits 15) in this process: later tests get the one before it
    signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def _tiny_spec(scene, out) -> SweepSpec:
    """Two runs (baseline and BAGS, 4 views, 5 deg, seed 0) of 4 iterations each."""
    return SweepSpec(scene=str(scene), out=out, rot_noises=(5,), views=(4,), seeds=(0,), refine_iters=2,
                     overrides=(("iters", 4), ("render_threads", 2)))


def test_ray_sweep_gives_the_local_results_and_resumes(scene, tmp_path, local_ray):
    local = run_sweep(_tiny_spec(scene, tmp_path / "local"), log=lambda message: None)
    messages = []
    # Two render threads in both (the spec's): the thread count changes results at rounding level; two CPUs per run.
    spec = _tiny_spec(scene, tmp_path / "ray")
    rows = run_sweep(spec, log=messages.append, executor=RayExecutor(cpus_per_run=2))
    names = [row["run"] for row in local]
    assert names == ["baseline-4v-rot5-seed0", "bags-4v-rot5-seed0"]
    assert messages[:2] == [f"train {name}" for name in names]
    assert sorted(messages[2:]) == sorted(f"finished {name}" for name in names)
    assert rows == local, (rows, local)
    assert json.loads((spec.out / "sweep.json").read_text()) == json.loads((tmp_path / "local" / "sweep.json").read_text())
    for name in ("sweep.csv", "psnr_vs_noise.png", "pose_error_vs_noise.png", "curves.png"):
        assert (spec.out / name).stat().st_size > 100, name
    # The runs went through the Ray tasks: they rendered with the two threads their tasks declared.
    for name in names:
        assert json.loads((spec.out / name / "config.json").read_text())["config"]["render_threads"] == 2

    # Resumable as the local executor: a second sweep over the folder (through the command line) runs nothing new.
    evals = {name: (spec.out / name / "eval.json").stat().st_mtime_ns for name in names}
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--seeds", "0",
                                 "--iters", "4", "--refine-iters", "2", "--out", str(spec.out), "--executor", "ray",
                                 "--cpus-per-run", "2"])
    assert result.exit_code == 0, result.output
    assert all(f"skip {name} (done)" in result.output for name in names) and "train " not in result.output
    assert evals == {name: (spec.out / name / "eval.json").stat().st_mtime_ns for name in names}
    assert json.loads((spec.out / "sweep.json").read_text()) == local
    # Other settings into the same folder are refused before anything runs: its table would mix them.
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4", "--seeds", "0",
                                 "--iters", "5", "--out", str(spec.out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "holds a run with iters=4, not 5" in lines[0], result.output
    assert evals == {name: (spec.out / name / "eval.json").stat().st_mtime_ns for name in names}


def test_a_ray_sweep_stopped_by_sigterm_exits_143_without_rays_stack_dump(scene, tmp_path):
    """Ray's core worker took SIGTERM with a native handler: a stack dump and exit 1. The sweep stops as a local one
    does: 143, "stopped by SIGTERM", Ray shut down."""
    import subprocess

    command = [sys.executable, "-m", "warpbags.cli.main", "sweep", str(scene), "--rot-noises", "5", "--views", "4",
               "--seeds", "0", "--iters", "400", "--out", str(tmp_path / "sweep"), "--executor", "ray"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})
    for line in process.stdout:
        if line.startswith("train "):  # every task submitted once the first line is out: Ray is up
            break
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    assert "stopped by SIGTERM" in stderr and "SIGTERM received" not in stderr, stderr[-3000:]


@pytest.mark.parametrize("options, named", [
    (["--executor", "foo"], "foo"),
    (["--executor", "ray", "--address", "127.0.0.1:1"], "127.0.0.1:1"),
    (["--executor", "ray", "--address", "nowhere"], "nowhere"),
    (["--address", "127.0.0.1:6379"], "--address"),
    (["--executor", "ray", "--cpus-per-run", "0"], "--cpus-per-run"),
    (["--executor", "ray", "--cpus-per-run", "2000"], "--cpus-per-run must be in [1, 1024], got 2000"),
])
def test_sweep_executor_bad_values_one_line(scene, tmp_path, options, named):
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4",
                                 "--out", str(tmp_path / "sweep"), *options])
    assert result.exit_code == 2, result.output
    assert named in result.output and result.output.strip().count("\n") == 0, result.output
    assert not ray.is_initialized() and not (tmp_path / "sweep").exists()  # refused before the folder is made


def test_sweep_on_ray_without_ray_names_the_extra(scene, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError, as where it is not installed
    result = runner.invoke(app, ["sweep", str(scene), "--rot-noises", "5", "--views", "4",
                                 "--out", str(tmp_path / "sweep"), "--executor", "ray"])
    assert result.exit_code == 2, result.output
    assert 'pip install -e ".[ray]"' in result.output and result.output.strip().count("\n") == 0, result.output
    assert not (tmp_path / "sweep").exists()  # before the scene is read and the sweep's folder made
