#!/usr/bin/env bash
# Sets up .venv (first run only) and runs the test suite on the CPU.
source "$(dirname "$0")/setup.sh"
exec python -m pytest -q "$@"
