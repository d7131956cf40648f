# Sourced by scripts/demo.sh and scripts/test.sh: creates .venv once and installs warpbags into it.
# CPU torch is pinned through constraints.txt (a bare `torch` requirement would pull a multi-GB CUDA build).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
# A .venv without a working pip (python3-venv missing when it was made, or a copied-in one) is made again.
if ! .venv/bin/python -m pip --version > /dev/null 2>&1; then
    rm -rf .venv
    python3 -m venv .venv
fi
stamp=.venv/.warpbags-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[test,ray]"
    touch "$stamp"
fi
export PATH="$PWD/.venv/bin:$PATH"
