#!/usr/bin/env bash
# Issue #16: the loop closing after a calibration that changed what the acquisition network depends on (the LEDs,
# the cameras' poses): usage `calibration_loop_with_networks_mini.sh L`, with L/cal written by `hemicube calibrate`.
# The true device captures `ramps` (seed 1) recording the truth, the calibrated rig and the nominal mini rig; a
# network is trained for the truth and for the calibrated rig with the shipped mini network's command (the shipped
# network serves the nominal rig), and each capture is reconstructed with its rig's network.
set -e
L=$1
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
