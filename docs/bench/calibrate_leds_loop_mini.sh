#!/usr/bin/env bash
# Issue #16, LEDs: the loop closing of docs/calibration.md (mini rig, perturbation seed 3, sample ramps, seed 1).
# A network is trained for the true device and for the calibrated rig (the shipped one serves the nominal rig):
# the network depends on the LED layout it was trained for.
set -e
L=/tmp/loopled
hemicube calibrate leds --rig mini --perturb 3 --no-progress -o $L/cal
T=$L/cal/truth R=$L/cal/rig
hemicube train --rig $T --steps 4000 --seed 0 --dropout 0 --no-progress -o $L/net_truth &
hemicube train --rig $R --steps 4000 --seed 0 --dropout 0 --no-progress -o $L/net_calibrated
wait
hemicube capture --rig $T --sample ramps --seed 1 --patterns $L/net_truth/patterns.npz --no-progress -o $L/caps_truth/true_rig
hemicube capture --rig $R --truth $T --sample ramps --seed 1 --patterns $L/net_calibrated/patterns.npz --no-progress \
    -o $L/caps_calibrated/calibrated_rig
hemicube capture --rig mini --truth $T --sample ramps --seed 1 --no-progress -o $L/caps_nominal/nominal_rig
hemicube reconstruct-many $L/caps_truth --network $L/net_truth --jobs 1 --no-progress -o $L/recon_truth
hemicube reconstruct-many $L/caps_calibrated --network $L/net_calibrated --jobs 1 --no-progress -o $L/recon_calibrated
hemicube reconstruct-many $L/caps_nominal --jobs 1 --no-progress -o $L/recon_nominal
