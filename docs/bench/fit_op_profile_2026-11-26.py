"""The paper-rig fit's kernels, one chunk (issue #12): torch.profiler's table of the loss evaluation
(_projected_loss), the Gauss-Newton system (_tensor_system) and one roughness / tangent candidate sweep.

    python docs/bench/fit_op_profile_2026-11-26.py OUT.txt

One fit chunk (reconstruction.fitting.AUTO_CHUNK_PAIRS texel-LED pairs: 5,461 paper-rig texels) of synthetic
texels (reconstruction.bench), the shipped compact network's decoded lumitexels, the lines as the primary view's
photos and 64 of them again as the secondary view's (the pipeline's photo counts: 63 + 64 and 64). A record of how
the numbers were measured, not part of the pipeline.
"""
import sys
import time

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

import twin
import reconstruction.fitting as F
from reconstruction.bench import _texels
from reconstruction.finetune import decoded_lumitexels, grey_to_rgb
from reconstruction.latents import decode
from reconstruction.pipeline import load_network

out = open(sys.argv[1], "w")
import os
dev = os.environ.get("DEV", "cuda:0")
rig = twin.load_rig(os.environ.get("RIG", "paper"))
model = load_network("pretrained", rig, dev)
upper = int((~np.asarray(rig.is_bottom)).sum())
n = min(F.AUTO_CHUNK_PAIRS // upper, int(os.environ.get("N_MAX", "1000000")))
learned, lines, pos, W, _ = _texels(rig, model, n, 0, dev, exact=False)
z = decode(model, learned, device=dev)
lumi = decoded_lumitexels(model, grey_to_rgb(z))
photos = np.concatenate([lines[:, 1:], lines], axis=1)
weights = np.concatenate([W[1:], W], axis=0)
cfg = F.FitConfig(device=dev)
prob = F._problem(rig, pos, lumi, photos, weights, None, cfg, (lines, W))
N = prob.frame[0].expand(prob.n, 3)
g = F._encode_geometry(N, torch.zeros(n, device=dev), torch.full((n,), 0.1, device=dev),
                       torch.full((n,), 0.05, device=dev), prob.frame, cfg)
geom = F._geometry(g, prob.frame, cfg)
q = torch.cat([g[:, :3], torch.log(geom["alpha_x"])[:, None], torch.log(geom["alpha_y"])[:, None]], 1)
x = F._to_tensor(q)
sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)
init_prob = F.replace(prob, photos=tuple(p for p in prob.photos if p.camera == cfg.camera))
work = {"_projected_loss": lambda: F._projected_loss(prob, F._log_geometry(q, prob.frame)),
        "_projected_loss_primary_only": lambda: F._projected_loss(init_prob, F._log_geometry(q, prob.frame)),
        "_tensor_system": lambda: F._tensor_system(prob, x),
        "_system": lambda: F._system(prob, q),
        "_best_candidate": lambda: F._best_candidate(init_prob, N)}
for name, fn in work.items():
    with torch.no_grad():
        fn()
        sync()
        t = time.perf_counter()
        fn()
        sync()
        s = time.perf_counter() - t
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
            fn()
            sync()
    out.write(f"=== {name}: {s * 1e3:.2f} ms wall ({n} texels)\n")
    out.write(p.key_averages().table(sort_by="cuda_time_total", row_limit=22) + "\n")
    print(name, f"{s * 1e3:.2f} ms", flush=True)
out.close()

# fine-tuning's pass 3, one Adam step of a 16,384-texel batch (FinetuneConfig.batch), with the rig's lines
if dev.startswith("cuda"):
    from reconstruction.finetune import _Problem as FTProblem
    b = 16384
    lt, ln, _, Wl, _ = _texels(rig, model, b, 1, dev, exact=False)
    x72 = torch.from_numpy(grey_to_rgb(decode(model, lt, device=dev))).to(dev).requires_grad_(True)
    with torch.enable_grad():
        for p_ in model.parameters():
            p_.requires_grad_(False)
        model.eval()
        ftp = FTProblem(model, torch.from_numpy(ln).to(dev), torch.from_numpy(Wl).to(dev), 8, 1e-6)
        opt = torch.optim.Adam([x72], lr=0.02)

        def step():
            opt.zero_grad(set_to_none=True)
            e = ftp.e3(x72)
            e.backward()
            opt.step()
            return float(e)
        step()
        sync()
        t = time.perf_counter()
        for _ in range(5):
            step()
        sync()
        s = (time.perf_counter() - t) / 5
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
            step()
            sync()
    with open(sys.argv[1], "a") as f:
        f.write(f"=== finetune pass-3 step: {s * 1e3:.2f} ms wall ({b} texels)\n")
        f.write(p.key_averages().table(sort_by="cuda_time_total", row_limit=22) + "\n")
    print("finetune pass-3 step", f"{s * 1e3:.2f} ms", flush=True)
