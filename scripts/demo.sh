#!/usr/bin/env bash
# Sets up .venv (first run only), then trains BAGS on the embedded maryrose capture: 4 views, every camera's pose
# perturbed by 15 degrees of rotation (std, random axes) and 0.3 scene units of camera-centre noise per axis (7.5%
# of the orbit radius), poses recovered jointly with the Gaussians (quick CPU preset), then evaluates on the
# held-out views and prints the pose errors before and after (sim(3) Procrustes-aligned). Extra arguments go to
# `warpbags train`; its --out (relative to where the script is called from) and --device are used by the evaluation
# too. Without --out the run goes to runs/ in the checkout.
caller="$PWD"
from_caller() { if [[ "$1" == /* ]]; then echo "$1"; else echo "$caller/$1"; fi; }
source "$(dirname "$0")/setup.sh"  # which moves to the checkout's root
out="runs/maryrose-4v-demo-$(date +%Y%m%d-%H%M%S)"
device=cpu
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
    case "${args[i]}" in
        --out) [[ -n "${args[i + 1]:-}" ]] && out="$(from_caller "${args[i + 1]}")" ;;
        --out=?*) out="$(from_caller "${args[i]#--out=}")" ;;
        --device) device="${args[i + 1]:-$device}" ;;
        --device=*) device="${args[i]#--device=}" ;;
    esac
done
warpbags train maryrose --views 4 --preset quick --rot-noise-deg 15 --trans-noise 0.3 "$@" --out "$out"
warpbags eval "$out" --procrustes --device "$device"
