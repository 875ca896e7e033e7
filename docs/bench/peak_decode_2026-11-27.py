"""Issue #13: the peak-term decoder's lumitexel written as max(expm1(y) + exp(z), 0) with z = [kappa c, log A - kappa]
. [d, 1] in float32 (reconstruction.network.Decoder.decode_lumitexel), against the form it replaces as the same-run
baseline: max(expm1(logaddexp(y, log A + kappa (c . d - 1))), 0) with c . d a matrix product in whatever precision the
caller allows (TF32 in fine-tuning on CUDA).

    python docs/bench/peak_decode_2026-11-27.py OUT.json [TEXELS]

1. Fine-tuning steps (forward, backward, Adam) of pass 1 and pass 3 on TEXELS paper-rig texels (`hemicube bench
   reconstruct`'s, the shipped network), TF32 allowed as the pipeline allows it, each form; milliseconds a step.
2. Same work: each form's latent gradient against the baseline form evaluated without TF32 (float32 products): the
   largest difference over the largest entry, and the median over texels of each texel's relative difference. In
   float32 the new form must agree within 1e-3 of the largest (exit 1 if not); with TF32, where the decoder's other
   products differ too, its texels' median must be no further from float32 than the baseline form's plus the
   forms' own float32 difference.
3. The shipped network's held-out figures (reconstruction.pretrained.score_network: Eq. 3 and the narrow lobes'),
   float32 and with TF32 allowed, each form: what TF32 in the peak's cosines costs.
A record of how the figures were measured, not part of the pipeline.
"""
import json
import sys

import torch

import reconstruction.network as N
from bench_setup import adam_step_ms, finetune_texels
from reconstruction.finetune import _frozen, _Problem, grey_to_rgb
from reconstruction.pretrained import TrainConfig, load_pretrained, score_network
from twin.optics.torch_ops import tf32_products

new_forward, new_decode = N.Decoder.forward, N.Decoder.decode_lumitexel


def old_forward(self, latent):  # the form before: kappa (c . d - 1) in the caller's precision, then logaddexp
    self._check(latent)
    h = self.net[:-1](latent)
    p = self.peak(h)
    c = p[:, :3] / p[:, :3].norm(dim=1, keepdim=True).clamp_min(1e-6)
    kappa = p[:, 3:4].clamp(N.PEAK_LOG_KAPPA[0], N.PEAK_LOG_KAPPA[1]).exp()
    return torch.logaddexp(self.net[-1](h), p[:, 4:5] + kappa * (c @ self.led_directions.T - 1.0))


def old_decode(self, latent):
    return N.log_to_lumitexel(old_forward(self, latent))


FORMS = {"logaddexp": (old_forward, old_decode), "direct": (new_forward, new_decode)}


def use(form):
    N.Decoder.forward, N.Decoder.decode_lumitexel = FORMS[form]


out_path, n = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 16384
dev = "cuda" if torch.cuda.is_available() else "cpu"
rig, model, lines, W, z, hold = finetune_texels("paper", n, dev)
prob = _Problem(model, torch.as_tensor(lines, device=dev), torch.as_tensor(W, device=dev), 8, 1e-6)
x56, x72 = torch.as_tensor(z, device=dev), torch.as_tensor(grey_to_rgb(z), device=dev)


def grad(energy, x0):
    g = x0.clone().requires_grad_(True)
    energy(g).backward()
    return g.grad


res = {"device": torch.cuda.get_device_name(0) if dev == "cuda" else "cpu", "texels": n, "steps": {}, "grad": {}}
passes = (("pass1", prob.e1, x56), ("pass3", prob.e3, x72))
with _frozen(model), torch.enable_grad():
    for rnd in (1, 2):  # two rounds, alternating, so that neither form alone pays the warm-up
        for form in FORMS:
            use(form)
            with tf32_products(True):
                for p, energy, x0 in passes:
                    res["steps"][f"{p}_{form}_ms_round{rnd}"] = adam_step_ms(energy, x0)
    use("logaddexp")
    with tf32_products(False):
        ref = {p: grad(e, x0) for p, e, x0 in passes}
    for form in FORMS:
        use(form)
        for tf32 in (True, False):
            with tf32_products(tf32):
                for p, e, x0 in passes:
                    g = grad(e, x0)
                    res["grad"][f"{p}_{form}_{'tf32' if tf32 else 'float32'}_max_rel_diff"] = \
                        float((g - ref[p]).abs().max() / ref[p].abs().max())
                    res["grad"][f"{p}_{form}_{'tf32' if tf32 else 'float32'}_median_rel_diff"] = \
                        float(((g - ref[p]).norm(dim=1) / ref[p].norm(dim=1).clamp_min(1e-30)).median())
net, info = load_pretrained("paper", dev)
cfg = TrainConfig.from_json(info["config"])
res["heldout"] = {"recorded": info["scores"]["heldout_loss"], "recorded_narrow": info["scores"]["narrow"]}
for form in FORMS:
    use(form)
    for tf32 in (False, True):
        with tf32_products(tf32):
            s = score_network(net, rig, cfg, dev)
        res["heldout"][f"{form}_{'tf32' if tf32 else 'float32'}"] = {"heldout_loss": s["heldout_loss"],
                                                                    "narrow": s["narrow"]}
use("direct")
res["passed"] = all(res["grad"][f"{p}_direct_float32_max_rel_diff"] <= 1e-3 and
                    res["grad"][f"{p}_direct_tf32_median_rel_diff"] <=
                    res["grad"][f"{p}_logaddexp_tf32_median_rel_diff"]
                    + res["grad"][f"{p}_direct_float32_median_rel_diff"]
                    for p, _, _ in passes)
print(json.dumps(res, indent=1))
with open(out_path, "w") as f:
    json.dump(res, f, indent=1)
sys.exit(0 if res["passed"] else 1)
