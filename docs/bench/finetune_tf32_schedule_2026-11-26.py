"""TF32 schedules for fine-tuning on the paper rig (issue #12: "mixed precision where it measurably does not hurt"),
an experiment: TF32 (torch's global flag for matrix products) in some passes or steps and float32 in the rest, against
float32 throughout, with the pipeline's default settings (FinetuneConfig(): the released caps and early-stopping rules).

    python docs/bench/finetune_tf32_schedule_2026-11-26.py 65536 > finetune_tf32_schedule_paper_h100_65536_2026-11-26.json

Runs (each from the same decoded latents of `hemicube bench reconstruct`'s synthetic texels, seed 0, with 1%
multiplicative photo noise on the lines and line 0 held out, as docs/bench/finetune_texel_stop_2026-11-26.py):
  float32          every product float32 (the pipeline today)
  tf32             every product TF32 (the 2026-11-25 run measured +1.5% median objective with the paper's counts)
  tf32_p12         TF32 in passes 1 and 2, float32 in pass 3
  tf32_finish20    TF32 until pass 3's rule stops a batch, then 20 more float32 steps of the same Adam
  float32_again    float32 once more (the same bits: the comparison is not run-to-run noise)
Reported per run: seconds, texel-steps per pass, the median per-texel pass-3 objective on the kept lines evaluated in
float32 and its difference from float32's (issue #12's rule: within 1%). Runs on the CPU too (TF32 is then a no-op),
e.g. with n = 64, to check the script.
"""
import sys, time, json, numpy as np, torch
from bench_setup import finetune_texels
from reconstruction import finetune as F

n = int(sys.argv[1])
dev = "cuda" if torch.cuda.is_available() else "cpu"
rig, model, lines, W, z, hold = finetune_texels("paper", n, dev)
original = F._adam_run


def tf32(on: bool) -> None:
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.backends.cudnn.allow_tf32 = on


class Later:
    """A stopping rule that stops `extra` steps after `rule` would have, calling `then()` when `rule` fires."""

    def __init__(self, rule, extra: int, then=lambda: None):
        self.rule, self.extra, self.then, self.fired = rule, extra, then, None

    def should_stop(self, hist) -> bool:
        if self.fired is None and self.rule.should_stop(hist):
            self.fired = len(hist)
            self.then()
        return self.fired is not None and len(hist) - self.fired >= self.extra


def scheduled(mode: str):
    def run(x0, energy, steps, lr, rule):
        pass3 = x0.shape[1] == 72
        if mode in ("float32", "tf32") or (mode == "tf32_p12"):
            tf32(mode == "tf32" or (mode == "tf32_p12" and not pass3))
            try:
                return original(x0, energy, steps, lr, rule)
            finally:
                tf32(False)
        # tf32_finish20: pass 3 in TF32 until its rule fires, then 20 float32 steps of the same Adam
        tf32(True)
        try:
            return original(x0, energy, steps, lr, Later(rule, 20, lambda: tf32(False)) if pass3 and rule else rule)
        finally:
            tf32(False)
    return run


res = {}
keep = [i for i in range(lines.shape[1]) if i not in hold]
for mode in ("float32", "tf32", "tf32_p12", "tf32_finish20", "float32_again"):
    F._adam_run = scheduled(mode.replace("_again", ""))
    if dev == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    ft = F.finetune(model, z, lines, W, F.FinetuneConfig(holdout=hold, device=dev))
    if dev == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t
    F._adam_run = original
    sim = F.simulate_lines(model, ft.latent, W, batch=16384)[:, keep]
    e = ((np.sqrt(np.maximum(sim, 0) + 1e-6) - np.sqrt(np.maximum(lines[:, keep], 0) + 1e-6)) ** 2).sum((1, 2))
    res[mode] = {"seconds": dt, "pass_seconds": ft.seconds,
                 "iterations": {k: [int(v) for v in vs] for k, vs in ft.iterations.items()},
                 "median_texel_objective": float(np.median(e)), "e": e}
a = res["float32"]["e"]
for mode, r in res.items():
    e = r.pop("e")
    r["median_objective_rel_diff"] = float((np.median(e) - np.median(a)) / np.median(a))
    r["texel_objective_rel_diff_median"] = float(np.median(np.abs(e - a) / np.maximum(a, 1e-12)))
res.update(rig="paper", texels=n, device=torch.cuda.get_device_name(0) if dev == "cuda" else "cpu",
           torch=torch.__version__)
print(json.dumps(res, indent=1))
