#!/bin/bash
# seventeenth session (issue #14, step 15): paper and paper@9003 on the paper rig at 192^2, the joint prior's loop of
# d72db1b (the old one: reconstruction/fitting.py from .gpu/old_fitting.py in a copy of the tree) and of step 15, one
# validate per GPU on a lent machine of four H100s. Needs Warp unpacked in /tmp/site (the two-call recipe) and the
# OpenEXR and tomli-w wheels installed there (the first call, which carries .whl beside .gpu/warp-a: the second call
# could not carry them too). Results (the validate JSONs, reconstruction.json, times) packed into $OUT.
R=$PWD
export PYTHONUNBUFFERED=1
Q=/tmp/q; mkdir -p $Q /tmp/old
tar cf - --exclude=./.gpu --exclude=./.whl --exclude=./.git . | tar xf - -C /tmp/old
cp .gpu/old_fitting.py /tmp/old/reconstruction/fitting.py
job() { local gpu=$1 tree=$2 tag=$3 s=$4
  ( cd $tree && export CUDA_VISIBLE_DEVICES=$gpu WARP_CACHE_PATH=/tmp/warp$gpu PYTHONPATH=/tmp/site:$tree
    echo start $tag $s $(date +%T) >> $Q/times.txt
    timeout ${LIMIT:-540} python -m hemicube.cli validate --rig paper --device cuda --resolution 192 --sample $s --json \
      --no-progress -o $Q/${tag}_$s > $Q/${tag}_$s.json 2> $Q/${tag}_$s.err
    echo end $tag $s rc=$? $(date +%T) >> $Q/times.txt ) &
}
job 0 $R new paper; job 1 $R new paper@9003; job 2 /tmp/old old paper; job 3 /tmp/old old paper@9003
wait
nvidia-smi --query-gpu=name --format=csv > $Q/gpu.txt
cd $Q && tar czf $OUT/s17.tgz times.txt gpu.txt *.json *.err $(ls -d */reconstruction/reconstruction.json 2>/dev/null)
ls -la $OUT
