#!/usr/bin/env bash
# Sets up .venv (first run only), then trains BAGS on the embedded maryrose capture: 4 views whose poses are
# perturbed by 15 degrees / 0.1 units, poses recovered jointly with the Gaussians (quick CPU preset).
# Extra arguments go to `warpbags train`.
source "$(dirname "$0")/setup.sh"
out="runs/maryrose-demo-$(date +%Y%m%d-%H%M%S)"
warpbags train maryrose --views 4 --preset quick --rot-noise-deg 15 --trans-noise 0.1 --out "$out" "$@"
