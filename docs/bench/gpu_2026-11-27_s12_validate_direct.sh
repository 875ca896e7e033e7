#!/bin/bash
# twelfth session, phase $1 on a lent machine of four H100s. Phase 1: GPU0 the peak decode bench, the held-out
# re-check, the CUDA tests, a mini capture's checksums, ramps 192^2; GPU1 ramps 1024^2 (stopped at the call's end,
# resumed in phase 2); GPUs 2, 3 suite samples at 192^2. Phase 2: GPU0 issue #12's end-to-end run; GPU1 ramps 1024^2
# resumed; GPU2 more samples at 192^2. Results in .gpu/q, packed into $OUT.
P=$1
source docs/bench/gpu_jobs.sh
if [ "$P" = 1 ]; then
  g 0 "cd docs/bench && timeout 170 python peak_decode_2026-11-27.py $Q/peak_decode.json 16384 > $Q/peak_decode.out 2>&1; echo rc=\$? >> $Q/peak_decode.out; cd $R" \
      "timeout 60 python -c \"from reconstruction.pretrained import heldout_loss; print('heldout_cuda', heldout_loss('paper', 'cuda'))\" > $Q/heldout.txt 2>&1" \
      "timeout 200 python -m pytest -q -rs tests/test_network.py tests/test_finetune.py tests/test_hdr.py tests/test_fit_sums.py tests/test_jvp.py tests/test_pretrained.py > $Q/pytest.txt 2>&1" \
      "timeout 90 python -m hemicube.cli capture --rig mini --device cuda -o $Q/mini_cap --no-progress > $Q/mini_cap.txt 2>&1; (cd $Q/mini_cap && find . -type f | sort | xargs sha256sum) > $Q/mini_cap_sha.txt"
  g 1 "$(V ramps 1024 550)"
  g 2 "$(V metal 192 280)" "$(V ceramic 192 255)"
  g 3 "$(V leather 192 280)" "$(V ramps 192 255)"
else
  g 0 "timeout 570 bash docs/bench/e2e_paper_1024.sh $Q/e2e_work $Q/e2e > $Q/e2e_sh.txt 2>&1; rm -rf $Q/e2e_work/S"
  g 1 "$(V ramps 1024 565)"
  g 2 "$(V satin 192 280)" "$(V wood 192 270)"
  g 3 "$(V woven 192 280)" "$(V fabric 192 270)"
fi
wait
nvidia-smi --query-gpu=name --format=csv > $Q/gpu.txt; df -h $R > $Q/df$P.txt
cd $Q && tar czf $OUT/q$P.tgz --exclude='*/capture/*' --exclude='*.exr' --exclude='*.npy' --exclude='*.npz' --exclude='*.safetensors' --exclude='*/images/*' --exclude='e2e_work' *.json *.txt *.out e2e 2>/dev/null $(ls -d v_*/report/report.md v_*/report/metrics.json v_*/reconstruction/reconstruction.json 2>/dev/null)
ls -la $OUT
