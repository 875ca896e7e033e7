#!/usr/bin/env bash
# Issues #18/#19 on the lent nvidia-h200-x2 (2 GPUs), part 1: DDP training N=2 and N=1 at the same global batch
# and wall time, then 4 paper-rig captures with capture-many on Ray over both GPUs. Needs Warp and Ray on
# PYTHONPATH (docs/scale-out.md). Writes its raw files to $OUT (default ./scaleout-out); runs in /tmp/so.
# NS: the process counts to train with, in order (default "2 1"); the captures use the first one's patterns.
set -u
OUT=${OUT:-$PWD/scaleout-out}; mkdir -p "$OUT" /tmp/so
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 PYTHONUNBUFFERED=1
LIMIT=${LIMIT:-150}
NS=${NS:-"2 1"}
FIRST=${NS%% *}
TRAIN="train --rig paper --device cuda --steps 200000 --batch 1024 --lr 5e-4 --eval-every 100 --checkpoint-every 1000000 --no-progress --time-limit $LIMIT"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$OUT/gpus.csv"
python3 -c "import torch, warp, ray; print('torch', torch.__version__, 'gpus', torch.cuda.device_count(), 'warp', warp.__version__, 'ray', ray.__version__)" | tee "$OUT/versions.txt"
for n in $NS; do
  t0=$(date +%s.%N)
  timeout 400 python3 -m torch.distributed.run --standalone --nproc_per_node=$n -m hemicube.cli $TRAIN -o /tmp/so/train$n > "$OUT/train$n.log" 2>&1
  echo "train N=$n rc=$? call_s=$(python3 -c "import time; print(round(time.time()-$t0,1))")" | tee -a "$OUT/steps.txt"
  cp /tmp/so/train$n/metrics.json "$OUT/train${n}_metrics.json"; cp /tmp/so/train$n/metrics.jsonl "$OUT/train${n}_metrics.jsonl"
done
cat > /tmp/so/samples.toml <<TOML
rig = "paper"
seed = 1
resolution = 256
patterns = "/tmp/so/train$FIRST/patterns.npz"
[[sample]]
name = "satin"
[[sample]]
name = "wood"
[[sample]]
name = "metal"
[[sample]]
name = "leather"
TOML
t0=$(date +%s.%N)
timeout 280 python3 -m hemicube.cli capture-many /tmp/so/samples.toml -o /tmp/so/caps --device cuda > "$OUT/capture_many.log" 2>&1
echo "capture-many rc=$? call_s=$(python3 -c "import time; print(round(time.time()-$t0,1))")" | tee -a "$OUT/steps.txt"
cp /tmp/so/caps/batch.json "$OUT/capture_many_batch.json"
du -sh /tmp/so/caps/* | tee -a "$OUT/steps.txt"
