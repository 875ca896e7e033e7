#!/bin/bash
# thirteenth session, phase $1 on a lent machine of four H100s: satin, wood and metal at 1024^2 with the shipped
# peak-term network and the per-frame photo weight (GPUs 0-2; stopped at phase 1's end and resumed in phase 2); the
# remaining samples at 192^2 on GPU 3 (paper and fabric first: the per-frame weight on the paper rig). Results in
# .gpu/q, packed into $OUT. Phase 3 (a third call, the budget's rest): paper again (phase 1 stopped it at its limit,
# the first run on the fresh machine), ceramic, leather and the held-back paper@9003 at 192^2, one per GPU.
P=$1
source docs/bench/gpu_jobs.sh
if [ "$P" = 1 ]; then
  g 0 "$(V satin 1024 560)"
  g 1 "$(V wood 1024 560)"
  g 2 "$(V metal 1024 560)"
  g 3 "$(V paper 192 280)" "$(V fabric 192 270)"
elif [ "$P" = 4 ]; then  # a fourth call: docs/bench/photo_errors_2026-11-27.py (its 90 s limit proved too short)
  E=$R/.gpu/pe; mkdir -p $E
  j() { local gpu=$1 s=$2; shift 2
    ( export CUDA_VISIBLE_DEVICES=$gpu WARP_CACHE_PATH=$R/.cache/warp$gpu
      timeout 150 python -m hemicube.cli capture --rig paper --device cuda --sample $s --seed 1 --resolution 128 -o $E/c_$s --no-progress
      for r in "$@"; do timeout 90 python docs/bench/photo_errors_2026-11-27.py $E/pe_${s}_$r.json cuda $r $E/c_$s; done
      rm -rf $E/c_$s ) > $E/log_$gpu.txt 2>&1 &
  }
  j 0 paper 192; j 1 fabric 192; j 2 paper@9003 192; j 3 ceramic 192; wait
  cd $E && tar czf $OUT/pe.tgz *.json log_*.txt
  exit
elif [ "$P" = 3 ]; then
  rm -rf $Q/v_*/capture
  i=0; for s in paper ceramic leather paper@9003; do
   ( export CUDA_VISIBLE_DEVICES=$i WARP_CACHE_PATH=$R/.cache/warp$i; echo start $s $(date +%T) >> $Q/times3.txt; timeout 330 python -m hemicube.cli validate --rig paper --device cuda --resolution 192 --sample $s --json --no-progress -o $Q/w_$s > $Q/w_$s.json 2> $Q/w_$s.err; echo end $s rc=$? $(date +%T) >> $Q/times3.txt ) & i=$((i+1)); done; wait
  cd $Q && tar czf $OUT/q3.tgz times3.txt w_*.json w_*.err $(ls -d w_*/report/report.md w_*/reconstruction/reconstruction.json 2>/dev/null)
  exit
else
  rm -rf $Q/v_*_192/capture
  g 0 "$(V satin 1024 565)"
  g 1 "$(V wood 1024 565)"
  g 2 "$(V metal 1024 565)"
  g 3 "$(V wallpaper 192 280)" "$(V quadrants 192 270)"
fi
wait
nvidia-smi --query-gpu=name --format=csv > $Q/gpu.txt; df -h $R > $Q/df$P.txt
cd $Q && tar czf $OUT/q$P.tgz --exclude='*/capture/*' --exclude='*.exr' --exclude='*.npy' --exclude='*.npz' --exclude='*.safetensors' *.json *.txt 2>/dev/null $(ls -d v_*/report/report.md v_*/report/metrics.json v_*/reconstruction/reconstruction.json 2>/dev/null)
for d in v_*_1024/report/images; do [ -d $d ] && tar czf $OUT/img_$(basename $(dirname $(dirname $d))).tgz $d; done
ls -la $OUT
