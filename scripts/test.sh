#!/usr/bin/env bash
# Sets up .venv (first run only) and runs the test suite on the CPU. Test paths given relative to the folder the
# script is called from are read from there (setup.sh moves to the checkout's root).
caller="$PWD"
args=()
expression=false  # the value of -k or -m is an expression, never a path
for arg in "$@"; do
    if ! $expression && [[ "$arg" != -* && "$arg" != /* && -e "$caller/${arg%%::*}" ]]; then
        arg="$caller/$arg"
    fi
    expression=false
    [[ "$arg" == -k || "$arg" == -m ]] && expression=true
    args+=("$arg")
done
source "$(dirname "$0")/setup.sh"
exec python -m pytest -q ${args[@]+"${args[@]}"}
