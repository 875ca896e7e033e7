"""Where a capture's fit spends its time, the joint prior above all (issue #12: capture + reconstruction of 1024^2
in 10 minutes; the joint prior took 112-135 s of a 1024^2 run whose Levenberg-Marquardt takes 4 s an iteration).

    python docs/bench/fit_capture_profile_2026-11-27.py OUT.json -- reconstruct S --device cuda --resolution 512 -o R

Runs `hemicube` with the arguments after `--`, every fitting function named below wrapped with a synchronised
timer (calls, seconds, texels), the checkpoint's saves too, and counts the texels _tensor_system treats as
isotropic. A record of how the numbers were measured, not part of the pipeline.
"""
import json
import sys
import time

import torch

import reconstruction.fitting as F
import reconstruction.pipeline as P
from bench_setup import timers
from hemicube.cli import main

out_path, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
stats, timed = timers()


def texels(prob, *rest):
    return int(prob.n)


for name in ("_initial", "_levenberg_marquardt", "_propagate", "_losses", "_final", "_joint_roughness",
             "_joint_albedos", "_tensor_system", "_normal_equations", "_loss", "_block_pcg", "_system",
             "_projected_loss", "_colour_weights", "_linearisation"):
    setattr(F, name, timed(name, getattr(F, name), texels if name in ("_tensor_system", "_normal_equations",
                                                                      "_projected_loss", "_linearisation") else None))
F._lumitexels_of = timed("_lumitexels_of", F._lumitexels_of, lambda src, idx, leds: int(idx.numel()))
F._isotropic_bases = timed("_isotropic_bases", F._isotropic_bases, texels)
P._Checkpoint.save = timed("checkpoint.save", P._Checkpoint.save)
t = time.perf_counter()
rc = main(args)
rec = {"argv": args, "rc": rc, "seconds": time.perf_counter() - t,
       "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
       "functions": {k: {"calls": v[0], "seconds": round(v[1], 3), **({"texels": v[2]} if v[2] else {})}
                     for k, v in sorted(stats.items(), key=lambda kv: -kv[1][1])}}
print(json.dumps(rec, indent=1))
with open(out_path, "w") as f:
    json.dump(rec, f, indent=1)
