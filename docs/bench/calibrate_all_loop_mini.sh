#!/usr/bin/env bash
# Issue #16: the loop closing of the whole calibration (docs/calibration.md, "Every procedure against one device"):
# the mini rig, perturbation seed 5 (cameras, flat field, colour, upper and bottom LEDs at once), every LED,
# sample ramps, seed 1. The networks depend on the cameras' poses and the LEDs.
set -e
L=/tmp/loopall1
hemicube calibrate all --rig mini --perturb 5 --board-scale 12 --views 4 --led-step 1 --no-progress -o $L/cal
bash "$(dirname "$0")/calibration_loop_with_networks_mini.sh" $L
