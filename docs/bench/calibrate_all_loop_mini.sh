#!/usr/bin/env bash
# Issue #16: the loop closing of the whole calibration (docs/calibration.md, "Every procedure against one device"):
# the mini rig, perturbation seed 5 (cameras, flat field, colour, upper and bottom LEDs at once), sample ramps,
# seed 1. The network depends on the cameras' poses and the LEDs, so one is trained for the truth and one for the
# calibrated rig with the shipped mini network's command; the nominal rig uses the shipped network.
set -e
L=/tmp/loopall1
hemicube calibrate all --rig mini --perturb 5 --board-scale 12 --views 4 --led-step 1 --no-progress -o $L/cal
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
