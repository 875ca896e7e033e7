"""usage: PYTHONPATH=. python3 docs/bench/fit_paper_h100.py TEXELS [BATCH]  (on a CUDA machine with Warp)

Time the GGX fit (reconstruction.fitting: Levenberg-Marquardt, per texel) on synthetic paper-rig texels on CUDA
against their exact lumitexels and lines (what `hemicube bench reconstruct` fits), and score it against the truth."""
import json, sys, time
import numpy as np, torch
import twin
from reconstruction.bench import _texels
from reconstruction.data import SamplingConfig, _generator, sample_parameters
from reconstruction.fitting import FitConfig, fit_ggx
from reconstruction.network import AcquisitionNet
from reconstruction.train import TrainConfig
rig = twin.load_rig("paper")
n = int(sys.argv[1])
dev = "cuda:0"
torch.manual_seed(0)
upper = int((~np.asarray(rig.is_bottom)).sum())
model = AcquisitionNet(TrainConfig(rig="paper").network_config(upper)).to(dev).eval()
learned, lines, pos, W, exact = _texels(rig, model, n, 0, dev, exact=True)
p = sample_parameters(n, SamplingConfig(), rig, _generator(0, "bench", 0))
out = {"texels": n, "device": torch.cuda.get_device_name(0), "rig": "paper", "leds_upper": upper}
for batch in ((int(sys.argv[2]),) if len(sys.argv) > 2 else (None,)):
    torch.cuda.synchronize(); t = time.perf_counter()
    fit = fit_ggx(rig, pos, exact, lines=lines, line_weights=W, config=FitConfig(device=dev, batch=batch))
    torch.cuda.synchronize(); dt = time.perf_counter() - t
    a_true = np.sqrt(p["alpha_x"].numpy() * p["alpha_y"].numpy())
    a_fit = np.sqrt(fit.alpha_x * fit.alpha_y)
    err = np.abs(np.log(a_fit / a_true))
    nt = p["normal"].numpy(); nt /= np.linalg.norm(nt, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip((fit.normal * nt).sum(1), -1, 1)))
    vis = p["rho_s"].numpy().mean(1) >= 0.5
    out["alpha_logerr_p90_rho_s_ge_0.5"] = float(np.percentile(err[vis], 90))
    out["rho_s_ge_0.5_fraction"] = float(vis.mean())
    out[f"batch_{batch}"] = {"seconds": dt, "per_1024sq_extrapolated_s": dt * 1024 * 1024 / n,
                             "alpha_logerr_median": float(np.median(err)), "alpha_logerr_p90": float(np.percentile(err, 90)),
                             "normal_deg_median": float(np.median(ang)),
                             "info": {k: v for k, v in fit.info.items() if k not in ("config", "texel_loss")}}
print(json.dumps(out, indent=1, default=float))
bad = err > 0.5
tilt = np.degrees(np.arccos(np.clip(nt[:, 2], -1, 1)))
ratio = np.maximum(p["alpha_x"].numpy(), p["alpha_y"].numpy()) / np.minimum(p["alpha_x"].numpy(), p["alpha_y"].numpy())
loss = fit.info["texel_loss"]


def q(x):
    return [round(float(v), 4) for v in np.percentile(x, [10, 50, 90])]


print(json.dumps({"bad_fraction": float(bad.mean()),
    "bad": {"alpha_true": q(a_true[bad]), "alpha_fit": q(a_fit[bad]), "ratio": q(ratio[bad]), "tilt": q(tilt[bad]), "rho_s": q(p["rho_s"].numpy().mean(1)[bad]), "rho_d": q(p["rho_d"].numpy().mean(1)[bad]), "loss": q(loss[bad])},
    "good": {"alpha_true": q(a_true[~bad]), "ratio": q(ratio[~bad]), "tilt": q(tilt[~bad]), "rho_s": q(p["rho_s"].numpy().mean(1)[~bad]), "loss": q(loss[~bad])},
    "sampling_alpha_range": [float(a_true.min()), float(a_true.max())]}, indent=1), file=sys.stderr)
