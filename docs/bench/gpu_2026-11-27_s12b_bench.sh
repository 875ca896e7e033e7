#!/bin/bash
# twelfth session, last call: the peak decode bench again (the product's backward in float32 too), then the
# reconstruction bench on 65,536 texels with the shipped network
R=$PWD
export PYTHONPATH=$R/.gpu/site:$R/.gpu/pylib:$R PYTHONUNBUFFERED=1 WARP_CACHE_PATH=$R/.cache/warp0
mkdir -p $OUT/b
(cd docs/bench && timeout 150 python peak_decode_2026-11-27.py $OUT/b/peak_decode.json 16384 > $OUT/b/peak_decode.out 2>&1; echo rc=$? >> $OUT/b/peak_decode.out)
timeout 270 python -m hemicube.cli bench reconstruct --rig paper --device cuda --texels 65536 > $OUT/b/bench_reconstruct.json 2> $OUT/b/bench_reconstruct_stderr.txt; echo rc=$? >> $OUT/b/bench_reconstruct_stderr.txt
nvidia-smi --query-gpu=name --format=csv >> $OUT/b/gpu.txt
