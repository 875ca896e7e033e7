#!/usr/bin/env bash
# Issue #12's end-to-end run on one GPU: a paper-rig capture of a 1024^2 sample and its reconstruction at a 1024^2
# grid, with an empty Warp kernel cache (compilation in the time), the device's used memory polled every 2 s; then
# `hemicube bench reconstruct` on 65,536 texels (the fit's and fine-tuning's precision checks). Each command runs
# under docs/bench/warp_compile_timed.py, which records the time its Warp kernel compilation took.
# Usage: docs/bench/e2e_paper_1024.sh WORK OUT   (WORK: a scratch folder; OUT: where the records go)
set -u
work=$1 out=$2
mkdir -p "$work" "$out"
export WARP_CACHE_PATH="$work/warp-cache"
rm -rf "$WARP_CACHE_PATH" "$work/S" "$work/R"
nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -l 2 > "$out/e2e_memory_mib.txt" &
smi=$!
{
  echo "device $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1)"
  echo "start $(date +%s.%N)"
  python docs/bench/warp_compile_timed.py "$out/capture_compile.json" -- \
    capture --rig paper --device cuda --resolution 1024 -o "$work/S" --no-progress
  echo "capture rc=$? $(date +%s.%N)"
  python docs/bench/warp_compile_timed.py "$out/reconstruct_compile.json" -- \
    reconstruct "$work/S" --device cuda --resolution 1024 -o "$work/R"
  echo "reconstruct rc=$? $(date +%s.%N)"
} > "$out/e2e_times.txt" 2> "$out/e2e_stderr.txt"
kill $smi
cp "$work/R/reconstruction.json" "$out/e2e_reconstruction.json"
python -m hemicube.cli bench reconstruct --rig paper --device cuda --texels 65536 > "$out/bench_reconstruct.json" \
  2> "$out/bench_reconstruct_stderr.txt"
echo "bench rc=$? $(date +%s.%N)" >> "$out/e2e_times.txt"
echo DONE >> "$out/e2e_times.txt"
