#!/usr/bin/env bash
# Sets up .venv (first run only), then trains BAGS on the embedded maryrose capture: 4 views whose poses are
# perturbed by 10 degrees (std, random axes), poses recovered jointly with the Gaussians (quick CPU preset,
# a few minutes on 2 cores), then evaluates on the held-out views. Extra arguments go to `warpbags train`.
source "$(dirname "$0")/setup.sh"
out="runs/maryrose-4v-demo-$(date +%Y%m%d-%H%M%S)"
warpbags train maryrose --views 4 --preset quick --rot-noise-deg 10 --out "$out" "$@"
warpbags eval "$out" --procrustes
