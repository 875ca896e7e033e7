#!/bin/bash
# phase 1 or 2: GPU0 trains the peak-term decoder (chunks, resumed on this machine); GPUs 1-3 validate the paper rig
# at 192^2 with the capture's default frames; results under .gpu/res, packed into $OUT
R=$PWD
export PYTHONPATH=$R/.gpu/site:$R/.gpu/pylib:$R PYTHONUNBUFFERED=1
mkdir -p .gpu/res
P=$1
g() { # GPU then commands
  local gpu=$1; shift
  ( export CUDA_VISIBLE_DEVICES=$gpu WARP_CACHE_PATH=$R/.cache/warp$gpu; for c in "$@"; do eval "$c"; done; echo done > .gpu/res/done$P$gpu ) > .gpu/res/log$P$gpu.txt 2>&1 &
}
T="python -m hemicube.cli train --rig paper --architecture compact --peak-term --dropout 0 --steps 1000000 --batch 1024 --lr 5e-4 --device cuda --eval-every 250 --checkpoint-every 10000000 --no-progress -o .gpu/res/peak"
V() { echo "timeout 570 python -m hemicube.cli validate --rig paper --device cuda --resolution 192 --sample $1 --json --no-progress -o .gpu/res/v_$1 > .gpu/res/v_$1.json"; }
if [ "$P" = 1 ]; then
  g 0 "$T --time-limit 500"
  g 1 "$(V ramps)"; g 2 "$(V paper)"; g 3 "$(V leather)"
else
  g 0 "$T --time-limit 470" "python -m hemicube.cli network ship .gpu/res/peak --device cuda -o .gpu/res/peakship > .gpu/res/peakship.json"
  g 1 "$(V metal)"; g 2 "$(V satin)"; g 3 "$(V ceramic)"
fi
wait
nvidia-smi --query-gpu=name --format=csv > .gpu/res/gpu.txt
cd .gpu/res && tar czf $OUT/res$P.tgz --exclude='*/capture/*' --exclude='*.safetensors' --exclude='checkpoint*' --exclude='*/images/*' --exclude='*.exr' --exclude='*.npy' *.json *.txt v_*/report/report.md v_*/report/metrics.json peak/metrics.json peak/metrics.jsonl 2>/dev/null
[ -f peakship/model.safetensors ] && cp peakship/model.safetensors peakship/model.json $OUT/
ls -la $OUT
