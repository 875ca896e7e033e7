#!/usr/bin/env bash
# Issue #16, vignetting: the loop closing of docs/calibration.md (mini rig, perturbation seed 3, sample ramps, seed 1).
set -e
hemicube calibrate vignetting --rig mini --perturb 3 --no-progress -o /tmp/loop/cal
T=/tmp/loop/cal/truth
hemicube capture --rig $T --sample ramps --seed 1 --no-progress -o /tmp/loop/caps/true_rig
hemicube capture --rig /tmp/loop/cal/rig --truth $T --sample ramps --seed 1 --no-progress -o /tmp/loop/caps/calibrated_rig
hemicube capture --rig mini --truth $T --sample ramps --seed 1 --no-progress -o /tmp/loop/caps/nominal_rig
hemicube reconstruct-many /tmp/loop/caps -o /tmp/loop/recon
