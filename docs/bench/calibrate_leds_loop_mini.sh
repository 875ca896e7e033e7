#!/usr/bin/env bash
# Issue #16, LEDs: the loop closing of docs/calibration.md (mini rig, perturbation seed 3, sample ramps, seed 1).
set -e
L=/tmp/loopled
hemicube calibrate leds --rig mini --perturb 3 --no-progress -o $L/cal
bash "$(dirname "$0")/calibration_loop_with_networks_mini.sh" $L
