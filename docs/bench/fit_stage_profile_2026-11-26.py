"""Where the paper-rig fit's time goes on a grid (issue #12: capture + reconstruction of 1024^2 in 10 minutes).

    python docs/bench/fit_stage_profile_2026-11-26.py G OUT.json

G x G synthetic paper-rig texels (reconstruction.bench's training-distribution texels, rendered exactly, the
shipped compact network), fine-tuned as `hemicube reconstruct` does, then fitted with grid_shape (G, G), so
that neighbour propagation and the joint prior run as in a capture's reconstruction (the bench's random texels
run neither). Every fitting function named below is wrapped with a synchronised timer, and the decoder's
lumitexel source with a call counter. A record of how the numbers were measured, not part of the pipeline.
"""
import json
import sys
import time

import torch

import twin
import reconstruction.fitting as F
from bench_setup import timers
from reconstruction.bench import _texels
from reconstruction.finetune import FinetuneConfig, decoded_lumitexels, finetune
from reconstruction.latents import decode
from reconstruction.pipeline import load_network

G, out_path = int(sys.argv[1]), sys.argv[2]
dev = "cuda:0"
rig = twin.load_rig("paper")
model = load_network("pretrained", rig, dev)
sync = torch.cuda.synchronize
rec = {"G": G, "texels": G * G, "device": torch.cuda.get_device_name(0)}

t = time.perf_counter()
learned, lines, pos, W, _ = _texels(rig, model, G * G, 0, dev, exact=False)
sync()
rec["synthesis_s"] = time.perf_counter() - t
t = time.perf_counter()
z = decode(model, learned, device=dev)
ft = finetune(model, z, lines, W, FinetuneConfig(holdout=(0,), device=dev))
sync()
rec["finetune_s"] = time.perf_counter() - t
rec["finetune_seconds"] = ft.seconds
rec["finetune_iterations"] = {k: sum(v) for k, v in ft.iterations.items()}

src = decoded_lumitexels(model, ft.latent, max_bytes=0)  # always a source, as at 1024^2
stats, timed = timers()


source = timed("decode (source)", src, count=lambda idx: idx.numel())
for name in ("_initial", "_levenberg_marquardt", "_propagate", "_losses", "_final", "_joint_roughness",
             "_joint_albedos", "_tensor_system", "_loss", "_block_pcg", "_system", "_projected_loss",
             "_lumitexels_of", "_target_mean"):
    setattr(F, name, timed(name, getattr(F, name)))

# the raw decoder on one fit chunk: what a decode pass could cost
idx = torch.arange(min(G * G, F.AUTO_CHUNK_PAIRS // 12288), device=dev)
src(idx)
sync()
t = time.perf_counter()
for _ in range(3):
    src(idx)
sync()
rec["decode_chunk"] = {"texels": idx.numel(), "seconds": (time.perf_counter() - t) / 3}

t = time.perf_counter()
fit = F.fit_ggx(rig, pos, source, lines=lines, line_weights=W, grid_shape=(G, G), config=F.FitConfig(device=dev))
sync()
rec["fit_s"] = time.perf_counter() - t
rec["fit_info"] = {k: v for k, v in fit.info.items() if isinstance(v, (int, float, str, list)) and k != "texel_loss"}
rec["functions"] = {k: {"calls": v[0], "seconds": v[1], **({"texels": v[2]} if v[2] else {})}
                    for k, v in sorted(stats.items(), key=lambda kv: -kv[1][1])}
rec["decode_passes"] = stats["decode (source)"][2] / (G * G)
print(json.dumps(rec, indent=1, default=str))
with open(out_path, "w") as f:
    json.dump(rec, f, indent=1, default=str)
