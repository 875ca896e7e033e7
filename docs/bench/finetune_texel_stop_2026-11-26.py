"""Per-texel early stopping against the released per-batch rule in fine-tuning (issue #12's "convergence-based
stopping per texel"), an experiment: the same texels, the same three passes, rules and caps; per texel, each texel
stops when ITS objective meets the rule (the batch's ratios computed on its own values) and leaves the batch, so
later steps cost less. Reports texel-steps (the decoder evaluations, the compute) and the per-texel pass-3 objective.

    python docs/bench/finetune_texel_stop_2026-11-26.py mini 2304 > finetune_texel_stop_mini_cpu_2304_2026-11-26.json

`hemicube bench reconstruct`'s synthetic texels (seed 0) with 1% multiplicative photo noise on the lines, line 0 held
out. Run on the mini rig on the CPU and on the paper rig on an H100 (`paper 65536 cuda`); neither saves steps
(docs/performance.md).
"""
import sys, time, json, numpy as np, torch
from bench_setup import finetune_texels
from reconstruction import finetune as F

rig_name, n = sys.argv[1], int(sys.argv[2]); dev = sys.argv[3] if len(sys.argv) > 3 else "cpu"
rig, model, lines, W, z, hold = finetune_texels(rig_name, n, dev)
cfg = F.FinetuneConfig(holdout=hold, device=dev, batch=16384)


def per_texel_e3(pb, x):
    sim = F._sim_rgb(pb.model, x, pb.w_lkc, pb.ad)
    return (torch.sqrt(sim + pb.eps) - pb.rgb_t[: x.shape[0]]).square().sum(dim=(1, 2))


def texel_objective(latent72):
    keep = [i for i in range(lines.shape[1]) if i not in hold]
    sim = F.simulate_lines(model, latent72, W, batch=16384)[:, keep]
    return ((np.sqrt(np.maximum(sim, 0) + 1e-6) - np.sqrt(np.maximum(lines[:, keep], 0) + 1e-6)) ** 2).sum((1, 2))


def adam_texel(x0, energy_rows, steps, lr, rule):
    """Adam (torch's formula, shared step count) on rows x0 (B, D); energy_rows(idx, x_rows) -> (len(idx),) per-texel
    objectives; each texel stops when the rule fires on its own objectives. Returns (x, texel-steps, steps per texel)."""
    x = x0.detach().clone()
    m, v = torch.zeros_like(x), torch.zeros_like(x)
    b1, b2, eps = 0.9, 0.999, 1e-8
    active = torch.arange(x.shape[0], device=x.device)
    hist = []  # per step: (B,) objective of every texel (NaN once stopped)
    done = torch.zeros(x.shape[0], dtype=torch.int64, device=x.device)
    cost = 0
    for s in range(steps):
        xa = x[active].requires_grad_(True)
        e = energy_rows(active, xa)
        g, = torch.autograd.grad(e.sum(), xa)
        t = s + 1
        ma = m[active].mul_(b1).add_(g, alpha=1 - b1)
        va = v[active].mul_(b2).addcmul_(g, g, value=1 - b2)
        m[active], v[active] = ma, va
        denom = (va.sqrt() / (1 - b2 ** t) ** 0.5).add_(eps)
        x[active] = xa.detach() - (lr / (1 - b1 ** t)) * ma / denom
        cost += active.numel(); done[active] += 1
        row = torch.full((x.shape[0],), float("nan"), device=x.device, dtype=torch.float64)
        row[active] = e.detach().double()
        hist.append(row)
        if rule is None or s < rule.lag:
            continue
        H = torch.stack(hist)  # (s+1, B)
        r = 100 * H[rule.lag:] / H[:-rule.lag]  # ratios r_j, j = lag..s
        nr = r.shape[0]
        if nr < rule.min_ratios or s < rule.min_step:
            continue
        mean = r[-rule.window:].mean(0)
        stop = (mean > rule.threshold)[active]
        active = active[~stop]
        if active.numel() == 0:
            break
    return x.detach(), cost, done


out = {"rig": rig_name, "texels": n, "device": dev}
# the released per-batch rule (reconstruction.finetune as shipped)
t = time.perf_counter()
res = F.finetune(model, z, lines, W, cfg)
out["batch_rule"] = {"seconds": time.perf_counter() - t, "iterations": res.iterations,
                     "texel_steps": [int(sum(it) * min(n, 16384)) for it in
                                     [[i for i in res.iterations[p]] for p in ("pass1", "pass2", "pass3")]]}
e_batch = texel_objective(res.latent)
out["batch_rule"]["median_texel_objective"] = float(np.median(e_batch))

# per texel: the same passes with each texel stopping on its own
keep = torch.tensor([i for i in range(lines.shape[1]) if i not in hold])
pb = F._Problem(model, torch.as_tensor(lines)[:, keep].to(dev), torch.as_tensor(W)[keep].to(dev), 8, 1e-6)
ad = 8
t = time.perf_counter()
with F._frozen(model), torch.enable_grad():
    zz = torch.as_tensor(z).to(dev)
    def e1(idx, x):
        mm = model.decode_lumitexel(x[:, :ad], x[:, ad:])
        return (torch.sqrt(mm @ pb.w0 + pb.eps) - pb.grey_t[idx]).square().sum(1)
    g1, c1, d1 = adam_texel(zz, e1, 500, 0.02, F.EARLY_STOP[0])
    rgb2 = torch.cat([g1[:, :ad]] * 3 + [g1[:, ad:]], 1).clone(); c2 = 0
    for c in range(3):
        s1 = g1[:, ad:]
        def e2(idx, a, c=c):
            mm = model.decode_lumitexel(a, s1[idx])
            return (torch.sqrt(mm @ pb.w0 + pb.eps) - pb.rgb_t[idx, :, c]).square().sum(1)
        a, cc, _ = adam_texel(g1[:, :ad], e2, 50, 0.05, F.EARLY_STOP[1]); c2 += cc
        rgb2[:, c * ad:(c + 1) * ad] = a
    def e3(idx, x):
        sim = F._sim_rgb(model, x, pb.w_lkc, ad)
        return (torch.sqrt(sim + pb.eps) - pb.rgb_t[idx]).square().sum(dim=(1, 2))
    x3, c3, d3 = adam_texel(rgb2, e3, 500, 0.02, F.EARLY_STOP[2])
e_texel = texel_objective(x3.cpu().numpy())
out["texel_rule"] = {"seconds": time.perf_counter() - t, "texel_steps": [c1, c2, c3],
                     "pass3_steps": {"median": float(d3.float().median()), "mean": float(d3.float().mean()),
                                     "max": int(d3.max())},
                     "median_texel_objective": float(np.median(e_texel))}
out["median_objective_rel_diff"] = (float(np.median(e_texel)) - float(np.median(e_batch))) / float(np.median(e_batch))
out["texel_objective_rel_diff_median"] = float(np.median((e_texel - e_batch) / np.maximum(e_batch, 1e-12)))
print(json.dumps(out, indent=1))
