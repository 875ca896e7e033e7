#!/bin/bash
# twelfth session: the sensor's fixed patterns drawn once per camera, on CUDA: a mini capture's bytes (against the
# CPU's) and the sensor bench
R=$PWD
export PYTHONPATH=$R/.gpu/site:$R/.gpu/pylib:$R PYTHONUNBUFFERED=1 WARP_CACHE_PATH=$R/.cache/warpc
mkdir -p $OUT/c
timeout 150 python -m hemicube.cli capture --rig mini --device cuda -o .gpu/c_cap --no-progress > $OUT/c/cap.txt 2>&1
(cd .gpu/c_cap && find . -type f | sort | xargs sha256sum) > $OUT/c/mini_cap_sha.txt
timeout 60 python docs/bench/sensor_fixed_arrays_2026-11-27.py $OUT/c/sensor_fixed_arrays_mini_cuda.json mini cuda 200 > $OUT/c/bench.txt 2>&1
timeout 60 python docs/bench/sensor_fixed_arrays_2026-11-27.py $OUT/c/sensor_fixed_arrays_paper_cuda.json paper cuda 50 > $OUT/c/bench_paper.txt 2>&1
nvidia-smi --query-gpu=name --format=csv >> $OUT/c/gpu.txt
