"""A plain (non-editable) `pip install .` imports the same way from the repository root as from anywhere else.

The source tree's `warpbags/` shadows an installed package whenever the repository root is on `sys.path` (it is,
as the current directory, for `python -c` run there), and the tree has no `kernels/`, `cli/` or `configs/` inside
`warpbags/`: they sit at the top, as the design card lays them out, and pyproject maps them into the namespace.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# What the wheel is built from: pyproject's package-dir sources and the readme it names.
BUILD_INPUTS = ("pyproject.toml", "README.md", "warpbags", "kernels", "cli", "configs")
MODULES = ("warpbags", "warpbags.kernels", "warpbags.cli.main", "warpbags.configs.train")

# The dev venv (scripts/setup.sh) holds an editable install whose import hook would find `warpbags.kernels` in the
# checkout on its own; a plain install has no such hook, so the child drops it before importing.
IMPORT_AND_LOCATE = f"""
import importlib, json, sys
sys.meta_path[:] = [finder for finder in sys.meta_path if not getattr(finder, "__module__", "").startswith("__editable__")]
print(json.dumps({{name: importlib.import_module(name).__file__ for name in {MODULES!r}}}))
"""


# The packaged maryrose scene read through the installed package (the editable hook dropped as above).
OPEN_MARYROSE = """
import json, sys
sys.meta_path[:] = [finder for finder in sys.meta_path
                    if not getattr(finder, "__module__", "").startswith("__editable__")]
from warpbags.data import open_scene
scene = open_scene("maryrose")
print(json.dumps({"root": str(scene.root), "views": scene.num_views, "images": list(scene.images.shape),
                  "masks": None if scene.masks is None else list(scene.masks.shape)}))
"""


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh non-editable install of the checkout, offline (no dependencies, no build isolation)."""
    # setuptools builds a wheel without the `wheel` package from 70.1 on
    pytest.importorskip("setuptools", minversion="70.1", reason="building the wheel offline needs setuptools >= 70.1")
    # Built from a copy: setuptools writes build/ and *.egg-info next to the sources it builds.
    source = tmp_path_factory.mktemp("source")
    for name in BUILD_INPUTS:
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        copy(ROOT / name, source / name, **({"ignore": shutil.ignore_patterns("__pycache__")} if copy is shutil.copytree else {}))
    target = tmp_path_factory.mktemp("site")
    command = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
               "--target", str(target), str(source)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (target / "warpbags" / "kernels" / "__init__.py").is_file()
    return target


def _run_from(directory: Path, site: Path, script: str) -> dict:
    """The JSON that `script` prints last, run by a fresh interpreter started in `directory` with `site` on its path."""
    environment = {**os.environ, "PYTHONPATH": str(site)}
    result = subprocess.run([sys.executable, "-c", script], cwd=directory, env=environment,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.splitlines()[-1])


def _import_from(directory: Path, site: Path) -> dict[str, str]:
    """Where each module of MODULES is imported from, by a fresh interpreter started in `directory`."""
    return {name: Path(path) for name, path in _run_from(directory, site, IMPORT_AND_LOCATE).items()}


def test_installed_package_imports_from_the_repository_root(installed):
    # The checkout shadows the install here, so every module comes from the checkout, kernels/ included.
    files = _import_from(ROOT, installed)
    assert files["warpbags"] == ROOT / "warpbags" / "__init__.py"
    assert files["warpbags.kernels"] == ROOT / "kernels" / "__init__.py"
    assert files["warpbags.cli.main"] == ROOT / "cli" / "main.py"
    assert files["warpbags.configs.train"] == ROOT / "configs" / "train.py"


def test_installed_package_imports_from_another_directory(installed, tmp_path):
    files = _import_from(tmp_path, installed)
    assert files["warpbags"] == installed / "warpbags" / "__init__.py"
    assert files["warpbags.kernels"] == installed / "warpbags" / "kernels" / "__init__.py"
    assert files["warpbags.cli.main"] == installed / "warpbags" / "cli" / "main.py"
    assert files["warpbags.configs.train"] == installed / "warpbags" / "configs" / "train.py"


def test_installed_package_ships_the_maryrose_scene(installed, tmp_path):
    """pyproject's package-data puts maryrose's poses, splits, images and masks in the wheel, so that `warpbags info
    maryrose` and the demo work from an install, away from the checkout."""
    scene = _run_from(tmp_path, installed, OPEN_MARYROSE)
    assert Path(scene["root"]) == installed / "warpbags" / "assets" / "maryrose"
    assert scene["views"] == 69 and scene["images"][0] == 69 and scene["masks"][0] == 69, scene
