"""Profile of the reconstruction stages on the GPU (issue #12), run at commit 2ad922d, before
reconstruction.fit_sums (the function names it wraps are that commit's): per-texel fine-tuning trajectories under
the released caps, the default and the paper's fine-tuning, the fit's time by function (inclusive, synchronised)
and torch's kernel tables for one chunk. A measurement script, not part of the package:

    PYTHONPATH=. python docs/bench/fit_profile_2026-11-25.py 4096 16384 paper

Output of the run on an H100, 2026-11-25: fit_profile_paper_h100_16384_2026-11-25.json (the kernel table of one
chunk's whole fit, from a second run: fit_profile_kernels_paper_h100_2730_2026-11-25.txt)."""
import json, os, sys, time, functools
sys.path.insert(0, os.getcwd())
import numpy as np
import torch
import twin
from reconstruction import bench as B, fitting as F, finetune as FT
from reconstruction.latents import decode
from reconstruction.pipeline import load_network
from reconstruction.finetune import FinetuneConfig, finetune, decode_rgb

out = os.environ.get("OUT", "/tmp/out")
dev = "cuda:0" if torch.cuda.is_available() else "cpu"
NT = int(sys.argv[1]) if len(sys.argv) > 1 else 4096     # trajectories
NF = int(sys.argv[2]) if len(sys.argv) > 2 else 16384    # fit profile
rig = twin.load_rig(sys.argv[3] if len(sys.argv) > 3 else "paper")
model = load_network("pretrained", rig, dev)
res = {"device": torch.cuda.get_device_name(0) if dev.startswith("cuda") else "cpu"}
t = time.perf_counter()
learned, lines, pos, W, _ = B._texels(rig, model, max(NT, NF), 0, dev, exact=False)
res["synth_s"] = time.perf_counter() - t
z = decode(model, learned, device=dev)

# --- A: per-texel trajectories, the code's caps, holdout 0
def sync():
    if dev.startswith("cuda"): torch.cuda.synchronize()
ad = model.config.albedo_dim
keep = torch.arange(1, lines.shape[1])
y = torch.as_tensor(lines[:NT][:, keep]).to(dev); w = torch.as_tensor(W[keep]).to(dev)
eps = 1e-6
pb = FT._Problem(model, y, w, ad, eps)
def per_texel(sim, tgt):
    return (torch.sqrt(sim + eps) - tgt).square().reshape(sim.shape[0], -1).sum(1)
e1 = lambda x: per_texel(model.decode_lumitexel(x[:, :ad], x[:, ad:]) @ pb.w0, pb.grey_t)
def run(x0, f, steps, lr):
    x = x0.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=lr)
    H = torch.empty(steps + 1, x.shape[0], device=dev)
    for s in range(steps):
        opt.zero_grad(); e = f(x); H[s] = e.detach(); e.sum().backward(); opt.step()
    with torch.no_grad(): H[steps] = f(x)
    return x.detach(), H
caps = (500, 50, 500)
with FT._frozen(model), torch.enable_grad():
    sync(); t = time.perf_counter()
    x1, H1 = run(torch.as_tensor(z[:NT]).to(dev), e1, caps[0], 0.02)
    sync(); res["traj_pass1_s"] = time.perf_counter() - t
    s1 = x1[:, ad:]
    H2 = []; a2 = []
    for c in range(3):
        f2 = lambda a, c=c: per_texel(model.decode_lumitexel(a, s1) @ pb.w0, pb.rgb_t[..., c])
        a, h = run(x1[:, :ad], f2, caps[1], 0.05); H2.append(h); a2.append(a)
    x2 = torch.cat(a2 + [s1], 1)
    f3 = lambda x: per_texel(FT._sim_rgb(model, x, pb.w_lkc, ad), pb.rgb_t)
    sync(); t = time.perf_counter()
    x3, H3 = run(x2, f3, caps[2], 0.02)
    sync(); res["traj_pass3_s"] = time.perf_counter() - t
np.save(f"{out}/traj_p12.npy", torch.cat([H1, torch.cat(H2, 0)], 0).cpu().numpy())
np.save(f"{out}/traj_p3.npy", H3.cpu().numpy())

# --- B: the pipeline's default fine-tuning (code, global stopping) on NF texels, and the paper's fixed counts
for src in ("code", "paper"):
    torch.cuda.reset_peak_memory_stats() if dev.startswith("cuda") else None
    sync(); t = time.perf_counter()
    ft = finetune(model, z[:NF], lines[:NF], W, FinetuneConfig(source=src, holdout=(0,), device=dev))
    sync()
    res[f"finetune_{src}"] = {"s": time.perf_counter() - t, "iterations": ft.iterations, "seconds": ft.seconds,
                             "objective": ft.objective,
                             "max_alloc_GiB": torch.cuda.max_memory_allocated() / 2**30 if dev.startswith("cuda") else 0}
    print(src, res[f"finetune_{src}"], flush=True)
lat = ft.latent
torch.cuda.empty_cache() if dev.startswith("cuda") else None

# --- C: the fit, time by function (inclusive, synchronised)
T = {}
def wrap(mod, name):
    f = getattr(mod, name)
    @functools.wraps(f)
    def g(*a, **k):
        sync(); t0 = time.perf_counter(); r = f(*a, **k); sync()
        d = T.setdefault(name, [0, 0.0, 0]); d[0] += 1; d[1] += time.perf_counter() - t0
        n = next((x.n for x in a if isinstance(x, F._Problem)), 0); d[2] += n
        return r
    setattr(mod, name, g)
for nm in ("_bases", "_photo_bases", "_albedo_sums", "_projected", "_loss_of", "_analytic_jacobian", "_residuals",
           "_initial", "_best_candidate", "_peak_normal", "_diffuse_normal", "_levenberg_marquardt", "_final",
           "_projected_loss", "_frame_derivatives", "_albedo_derivatives", "_photo_dterms", "_solve_box"):
    wrap(F, nm)
import twin.optics.jvp as J
wrap(J, "basis_jvp")
wrap(twin, "lumitexels")
lumi = decode_rgb(model, lat)
torch.cuda.reset_peak_memory_stats() if dev.startswith("cuda") else None
sync(); t = time.perf_counter()
fit = F.fit_ggx(rig, pos[:NF], lumi, lines=lines[:NF], line_weights=W, config=F.FitConfig(device=dev))
sync()
res["fit_s"] = time.perf_counter() - t
res["fit_info"] = {k: v for k, v in fit.info.items() if isinstance(v, (int, float, str))}
res["fit_history"] = fit.history
res["fit_max_alloc_GiB"] = torch.cuda.max_memory_allocated() / 2**30 if dev.startswith("cuda") else 0
res["fit_by_function"] = {k: {"calls": v[0], "s": round(v[1], 4), "texels": v[2]} for k, v in sorted(T.items(), key=lambda kv: -kv[1][1])}
np.save(f"{out}/fit_loss.npy", fit.info["texel_loss"])
print(json.dumps(res["fit_by_function"], indent=1), flush=True)

# --- D: torch profiler on one chunk: a candidate evaluation and one Jacobian + residuals
if dev.startswith("cuda"):
    from torch.profiler import profile, ProfilerActivity
    prob = F._problem(rig, pos[:NF], lumi, lines[:NF], W, None, F.FitConfig(device=dev))
    idx = next(iter(F._chunks(prob, None)))
    part = prob.part(idx)
    q = torch.zeros(part.n, 5, device=dev); q[:, 3:] = -2.0
    with torch.no_grad():
        F._residuals(part, q); F._analytic_jacobian(part, q); sync()
        for label, fn in (("residuals", lambda: F._residuals(part, q)), ("jacobian", lambda: F._analytic_jacobian(part, q)),
                          ("candidate", lambda: F._projected_loss(part, F._log_geometry(q, part.frame)))):
            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
                fn(); sync()
            tab = p.key_averages().table(sort_by="self_cuda_time_total", row_limit=25)
            open(f"{out}/prof_{label}.txt", "w").write(tab)
            print(label, tab[:3000], flush=True)
json.dump(res, open(f"{out}/prof12.json", "w"), indent=1, default=str)
print("done", flush=True)
