#!/bin/bash
# the paper rig at 192^2 with the shipped network and the capture's default frames: 8 samples, two per GPU
R=$PWD
export PYTHONPATH=$R/.gpu/site:$R/.gpu/pylib:$R PYTHONUNBUFFERED=1
mkdir -p .gpu/r3
g() { local gpu=$1; shift
  ( export CUDA_VISIBLE_DEVICES=$gpu WARP_CACHE_PATH=$R/.cache/warp$gpu; for c in "$@"; do eval "$c"; done ) > .gpu/r3/log$gpu.txt 2>&1 &
}
V() { echo "timeout 290 python -m hemicube.cli validate --rig paper --device cuda --resolution 192 --sample $1 --json --no-progress -o .gpu/r3/v_$1 > .gpu/r3/v_$1.json; date >> .gpu/r3/times.txt; echo $1 >> .gpu/r3/times.txt"; }
date > .gpu/r3/times.txt
g 0 "$(V ramps)" "$(V ceramic)"; g 1 "$(V paper)" "$(V satin)"; g 2 "$(V leather)" "$(V wood)"; g 3 "$(V metal)" "$(V fabric)"
wait
nvidia-smi --query-gpu=name --format=csv > .gpu/r3/gpu.txt
cd .gpu/r3 && tar czf $OUT/res3.tgz *.json *.txt v_*/report/report.md v_*/report/metrics.json
ls -la $OUT
