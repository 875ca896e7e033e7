#!/usr/bin/env bash
# Issue #16, colour: the loop closing of docs/calibration.md (mini rig, perturbation seed 3, sample ramps, seed 1).
# The crosstalk is not part of the rig's geometry (Rig.geometry_digest), so the shipped network serves all three.
set -e
L=/tmp/loopcolour
hemicube calibrate colour --rig mini --perturb 3 --no-progress -o $L/cal
T=$L/cal/truth
hemicube capture --rig $T --sample ramps --seed 1 --no-progress -o $L/caps/true_rig
hemicube capture --rig $L/cal/rig --truth $T --sample ramps --seed 1 --no-progress -o $L/caps/calibrated_rig
hemicube capture --rig mini --truth $T --sample ramps --seed 1 --no-progress -o $L/caps/nominal_rig
hemicube reconstruct-many $L/caps --jobs 2 --no-progress -o $L/recon
