#!/usr/bin/env bash
# Issues #18/#19 on the lent nvidia-h200-x2, part 2 (right after part 1, same machine): reconstruct-many over the
# 4 paper-rig captures on G GPUs (argument 1 or 2; with 1, CUDA_VISIBLE_DEVICES=0 so that Ray sees one), each into
# its own folder, with the network part 1 trained first (NET, default /tmp/so/train2). Usage:
# scaleout_h200x2_reconstruct.sh G...
set -u
OUT=${OUT:-$PWD/scaleout-out}; mkdir -p "$OUT"
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1 PYTHONUNBUFFERED=1
GRID=${GRID:-64}
NET=${NET:-/tmp/so/train2}
LIMIT=${LIMIT:-420}
for g in "$@"; do
  vis=$([ $g = 1 ] && echo 0 || echo 0,1)
  t0=$(date +%s.%N)
  CUDA_VISIBLE_DEVICES=$vis timeout $LIMIT python3 -m hemicube.cli reconstruct-many /tmp/so/caps -o /tmp/so/recon$g --device cuda \
      --network $NET --resolution $GRID > "$OUT/reconstruct_many_${g}gpu.log" 2>&1
  echo "reconstruct-many gpus=$g rc=$? call_s=$(python3 -c "import time; print(round(time.time()-$t0,1))")" | tee -a "$OUT/steps.txt"
  cp /tmp/so/recon$g/batch.json "$OUT/reconstruct_many_${g}gpu_batch.json"
  # the per-capture logs and each reconstruction's summary (stage seconds, alignment info), in one file
  (cd /tmp/so/recon$g && tar czf "$OUT/reconstruct_many_${g}gpu_logs.tgz" logs */reconstruction.json 2>/dev/null)
done
