# Sourced by the dated runner scripts here (gpu_2026-11-27_s12_validate_direct.sh, gpu_2026-11-27_s13_validate.sh),
# from the repository root on a lent GPU machine, with P set to the phase: the unpacked Warp and wheels on the path,
# the results folder Q, and two helpers.
R=$PWD
export PYTHONPATH=$R/.gpu/site:$R/.gpu/pylib:$R PYTHONUNBUFFERED=1
Q=$R/.gpu/q; mkdir -p $Q
# g GPU COMMAND...: the commands one after another on one GPU (its own Warp kernel cache), in the background
g() { local gpu=$1; shift
  ( export CUDA_VISIBLE_DEVICES=$gpu WARP_CACHE_PATH=$R/.cache/warp$gpu; for c in "$@"; do eval "$c"; done; echo "done $(date +%T)" >> $Q/done$P$gpu ) > $Q/log$P$gpu.txt 2>&1 &
}
# V SAMPLE RES LIMIT: validate, then drop the capture (34 GB with four frames) once scored
V() { echo "echo start $1 $2 \$(date +%T) >> $Q/times.txt; timeout $3 python -m hemicube.cli validate --rig paper --device cuda --resolution $2 --sample $1 --json --no-progress -o $Q/v_$1_$2 > $Q/v_$1_$2.json; echo end $1 $2 rc=\$? \$(date +%T) >> $Q/times.txt; [ -s $Q/v_$1_$2.json ] && rm -rf $Q/v_$1_$2/capture"; }
