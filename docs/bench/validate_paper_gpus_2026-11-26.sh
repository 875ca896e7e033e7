#!/bin/bash
# How the 2026-11-26 (third session) paper-rig runs were made on a lent machine of four H100s (docs/accuracy.md):
# one `hemicube validate --rig paper --device cuda` per GPU at the same time, each with its own Warp kernel cache,
# started in a process session of its own so that it outlives the device call that starts it (later calls poll the
# logs), each run's report, reconstruction summary and map panels (as JPEG) packed into one file a run.
#
#   bash docs/bench/validate_paper_gpus_2026-11-26.sh GPU:SAMPLE:RESOLUTION ...
#   e.g. 0:wood:1024 1:metal:1024 2:paper:1024 "3:leather:256 3:wallpaper:256"   (one quoted group runs in turn)
#
# Writes .gpu/out/SAMPLE_RES/ (the runs), .gpu/logs/SAMPLE_RES.log, .gpu/results/SAMPLE_RES.tar.gz and, when every
# run has ended, .gpu/logs/ALLDONE. Expects Warp and the wheels already unpacked in .gpu/site and .gpu/pylib.
# The lent machine goes back 30 s after a call ends, with the runs and their files: poll with calls back to back
# (e.g. `sleep 400; tail ...`), and fetch each run's tarball as soon as it is there (2026-11-26: four 1024^2 runs lost).
R=$PWD
export PYTHONPATH=$R/.gpu/site:$R/.gpu/pylib:$R PYTHONUNBUFFERED=1
mkdir -p .gpu/logs .gpu/out .gpu/results
pack() {  # NAME
  python - "$1" <<'PY'
import io, pathlib, sys, tarfile
from PIL import Image
name = sys.argv[1]
out = pathlib.Path(".gpu/out") / name
with tarfile.open(f".gpu/results/{name}.tar.gz", "w:gz") as t:
    for p in (out / "report" / "metrics.json", out / "report" / "report.md", out / "reconstruction" / "reconstruction.json",
              pathlib.Path(f".gpu/logs/{name}.log")):
        if p.exists():
            t.add(p, arcname=f"{name}/{p.name}")
    for p in sorted((out / "report" / "images").glob("*.png")):
        b = io.BytesIO()
        Image.open(p).convert("RGB").save(b, "JPEG", quality=85)
        info = tarfile.TarInfo(f"{name}/images/{p.stem}.jpg")
        info.size = b.getbuffer().nbytes
        b.seek(0)
        t.addfile(info, b)
PY
}
one() {  # GPU SAMPLE RESOLUTION
  local name=$2_$3
  echo "start $(date +%T)" > .gpu/logs/$name.log
  CUDA_VISIBLE_DEVICES=$1 WARP_CACHE_PATH=$R/.cache/warp$1 python -m hemicube.cli validate --rig paper --device cuda \
    --resolution $3 --sample $2 -o .gpu/out/$name >> .gpu/logs/$name.log 2>&1
  echo "rc=$? end $(date +%T)" >> .gpu/logs/$name.log
  pack $name
}
(nvidia-smi --query-gpu=index,memory.used,utilization.gpu --format=csv -l 10 > .gpu/logs/smi.log 2>&1 &)
for group in "$@"; do
  ( for job in $group; do IFS=: read -r gpu sample res <<< "$job"; one "$gpu" "$sample" "$res"; done ) &
done
wait
echo ALLDONE > .gpu/logs/ALLDONE
