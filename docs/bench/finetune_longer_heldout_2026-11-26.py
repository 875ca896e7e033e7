"""Does fine-tuning stop too early for the held-out line? (docs/accuracy.md, "A lead on the latent render"), an
experiment on the paper rig: the same decoded latents fine-tuned (float32) with the pipeline's stopping rule, with 20
more pass-3 steps after the rule stops a batch, and at the paper's fixed counts (100/50/200); for each, the median
per-texel objective on the kept lines and the held-out line's error per texel against the exact (noise-free) line,
relative to the texel's mean line, i.e. what the latent render of a held-out photo measures, without the photo's noise.

    python docs/bench/finetune_longer_heldout_2026-11-26.py 65536 > finetune_longer_heldout_paper_h100_65536_2026-11-26.json

Texels: `hemicube bench reconstruct`'s synthetic ones (seed 0), the shipped paper-rig network, 1% multiplicative noise
on the fine-tuned lines, line 0 held out (as docs/bench/finetune_texel_stop_2026-11-26.py). Runs on the CPU too.
"""
import sys, time, json, numpy as np, torch, twin
from reconstruction.bench import _texels
from reconstruction.pipeline import load_network
from reconstruction.latents import decode
from reconstruction import finetune as F

n = int(sys.argv[1])
dev = "cuda" if torch.cuda.is_available() else "cpu"
torch.manual_seed(0)
rig = twin.load_rig("paper")
model = load_network("pretrained", rig, dev)
learned, exact, pos, W, _ = _texels(rig, model, n, 0, dev, exact=False)
rng = np.random.default_rng(1)
lines = (exact * (1 + 0.01 * rng.standard_normal(exact.shape))).astype(np.float32)
z = decode(model, learned, device=dev)
hold = (0,)
keep = [i for i in range(lines.shape[1]) if i not in hold]
original = F._adam_run


def finish(extra: int):
    def run(x0, energy, steps, lr, rule):
        if x0.shape[1] != 72 or rule is None:
            return original(x0, energy, steps, lr, rule)
        x = x0.detach().clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=lr, betas=(0.9, 0.999))
        hist, done, fired = [], 0, None
        for _ in range(steps):
            opt.zero_grad(set_to_none=True)
            e = energy(x)
            e.backward()
            opt.step()
            done += 1
            hist.append(float(e.detach()))
            if fired is None and rule.should_stop(hist):
                fired = done
            if fired is not None and done - fired >= extra:
                break
        return x.detach(), hist, done
    return run


F.finetune(model, z[:16384], lines[:16384], W, F.FinetuneConfig(iterations=(1, 1, 1), holdout=hold, device=dev,
                                                                   precision="float32"))  # warm-up, untimed
res = {}
for name, cfg, runner in (
        ("rule", F.FinetuneConfig(holdout=hold, device=dev, precision="float32"), original),
        ("rule_plus20", F.FinetuneConfig(holdout=hold, device=dev, precision="float32"), finish(20)),
        ("rule_plus60", F.FinetuneConfig(holdout=hold, device=dev, precision="float32"), finish(60)),
        ("paper_counts", F.FinetuneConfig(source="paper", holdout=hold, device=dev, precision="float32"), original)):
    F._adam_run = runner
    if dev == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    ft = F.finetune(model, z, lines, W, cfg)
    if dev == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t
    F._adam_run = original
    sim = F.simulate_lines(model, ft.latent, W, batch=16384)
    e = ((np.sqrt(np.maximum(sim[:, keep], 0) + 1e-6) - np.sqrt(np.maximum(lines[:, keep], 0) + 1e-6)) ** 2).sum((1, 2))
    # per texel, relative to its mean line (a held-out line can be near zero where it lights nothing the texel shows)
    scale = np.maximum(np.abs(exact).sum((1, 2)) / exact.shape[1], 1e-12)
    held = np.abs(sim[:, 0] - exact[:, 0]).sum(1) / scale
    kept = np.abs(sim[:, keep] - exact[:, keep]).sum((1, 2)) / len(keep) / scale
    res[name] = {"seconds": dt, "pass3_steps": [int(v) for v in ft.iterations["pass3"]],
                 "median_texel_objective": float(np.median(e)),
                 "heldout_line_rel_err_vs_exact": {"median": float(np.median(held)), "p90": float(np.percentile(held, 90))},
                 "kept_lines_rel_err_vs_exact_median": float(np.median(kept))}
res.update(rig="paper", texels=n, device=torch.cuda.get_device_name(0) if dev == "cuda" else "cpu",
           torch=torch.__version__)
print(json.dumps(res, indent=1))
