"""scripts/demo.sh passes its extra arguments to `warpbags train` and evaluates the run that training wrote, on the
device it trained on (the warpbags commands replaced by a stub that records them)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _demo_commands(tmp_path: Path, *args: str) -> list[list[str]]:
    """Run a copy of demo.sh whose setup puts a stub `warpbags` first on PATH; returns the commands it ran."""
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    shutil.copy(ROOT / "scripts" / "demo.sh", scripts / "demo.sh")
    stub_bin = tmp_path / "bin"
    stub_bin.mkdir()
    log = tmp_path / "commands.txt"
    stub = stub_bin / "warpbags"
    stub.write_text(f'#!/usr/bin/env bash\nprintf "%s\\t" "$@" >> "{log}"\necho >> "{log}"\n')
    stub.chmod(0o755)
    # as the real setup.sh, it moves to the checkout's root; the demo is called from a folder of the user's
    (scripts / "setup.sh").write_text(f'set -euo pipefail\ncd "{tmp_path}"\nexport PATH="{stub_bin}:$PATH"\n')
    caller = tmp_path / "caller"
    caller.mkdir()
    subprocess.run(["bash", str(scripts / "demo.sh"), *args], check=True, cwd=caller, timeout=60)
    return [line.rstrip("\t").split("\t") for line in log.read_text().splitlines()]


def _last_out(arguments: list[str]) -> str | None:
    """The --out value a command line ends up with (the last one given, as click takes it)."""
    value = None
    for index, argument in enumerate(arguments):
        if argument == "--out":
            value = arguments[index + 1]
        elif argument.startswith("--out="):
            value = argument.removeprefix("--out=")
    return value


@pytest.mark.parametrize("extra, out, device", [
    ((), None, "cpu"),
    (("--out", "elsewhere", "--device", "cuda"), "caller/elsewhere", "cuda"),
    (("--out=elsewhere", "--device=cuda", "--iters", "10"), "caller/elsewhere", "cuda"),
    (("--out", "/absolute/run"), "/absolute/run", "cpu"),
])
def test_demo_evaluates_the_folder_and_device_training_used(tmp_path, extra, out, device):
    """Every extra argument reaches `warpbags train`; a relative --out is the caller's, not the checkout's (setup.sh
    moves to the checkout: `bash ~/warpbags/scripts/demo.sh --out run` wrote ~/warpbags/run)."""
    train, evaluate = _demo_commands(tmp_path, *extra)
    assert train[:2] == ["train", "maryrose"]
    assert train[len(train) - len(extra) - 2:len(train) - 2] == list(extra)
    trained_into = _last_out(train)
    if out is None:
        assert trained_into.startswith("runs/maryrose-4v-demo-")
    elif out.startswith("/"):
        assert trained_into == out
    else:
        assert trained_into == str(tmp_path / out)
    assert evaluate[:2] == ["eval", trained_into]
    assert evaluate[evaluate.index("--device") + 1] == device


def _option_values(arguments: list[str]) -> dict[str, str | None]:
    """Each `--option value` (or a flag, None) of a command line, by option."""
    values = {}
    for index, argument in enumerate(arguments):
        if argument.startswith("--"):
            following = arguments[index + 1] if index + 1 < len(arguments) else None
            values[argument] = None if following is None or following.startswith("--") else following
    return values


def test_demo_trains_four_noisy_views_on_the_quick_preset_and_evaluates_aligned(tmp_path):
    """What the demo shows (its header): 4 views, 15 deg of rotation and 0.3 of camera-centre noise to recover, the
    CPU-sized preset, and pose errors after sim(3) Procrustes alignment (the run's frame is not the scene's)."""
    train, evaluate = _demo_commands(tmp_path)
    options = _option_values(train)
    assert {name: options.get(name) for name in ("--views", "--preset", "--rot-noise-deg", "--trans-noise")} == {
        "--views": "4", "--preset": "quick", "--rot-noise-deg": "15", "--trans-noise": "0.3"}, train
    assert "--procrustes" in evaluate, evaluate


def test_the_test_script_and_ci_take_paths_from_where_they_are_called(tmp_path):
    """scripts/test.sh moved to the checkout's root before pytest read its arguments, so `bash ../scripts/test.sh
    test_x.py` from tests/ found no file; .ci/run ran `scripts/test.sh` relative to the caller's folder (rc 127
    anywhere but the root). A copy whose setup is a stub, and a pytest stub that records what it is given."""
    checkout = tmp_path / "checkout"
    (checkout / "scripts").mkdir(parents=True)
    (checkout / ".ci").mkdir()
    shutil.copy(ROOT / "scripts" / "test.sh", checkout / "scripts" / "test.sh")
    shutil.copy(ROOT / ".ci" / "run", checkout / ".ci" / "run")
    log = tmp_path / "pytest-arguments.txt"
    stub_bin = tmp_path / "bin"
    stub_bin.mkdir()
    (stub_bin / "python").write_text(f'#!/usr/bin/env bash\nprintf "%s\\n" "$PWD" "$@" > "{log}"\n')
    (stub_bin / "python").chmod(0o755)
    (checkout / "scripts" / "setup.sh").write_text(f'set -euo pipefail\ncd "{checkout}"\nexport PATH="{stub_bin}:$PATH"\n')
    caller = tmp_path / "caller"
    caller.mkdir()
    (caller / "test_x.py").write_text("")
    subprocess.run(["bash", str(checkout / "scripts" / "test.sh"), "test_x.py::test_one", "-k", "test_x.py", "-q"],
                   check=True, cwd=caller, timeout=60)
    assert log.read_text().splitlines() == [str(checkout), "-m", "pytest", "-q", f"{caller}/test_x.py::test_one", "-k",
                                            "test_x.py", "-q"]
    has_chromium = Path("/usr/bin/chromium").exists()  # .ci/run installs it first where it is missing
    if has_chromium:
        subprocess.run(["bash", str(checkout / ".ci" / "run")], check=True, cwd=caller, timeout=60)
        assert log.read_text().splitlines() == [str(checkout), "-m", "pytest", "-q"]
