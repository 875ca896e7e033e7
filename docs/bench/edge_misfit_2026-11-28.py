"""Paper's stock by distance to ink or foil, and each texel's misfit at the joint prior's start (issue #14, eighteenth
session): can a texel's own misfit tell the mixed texels next to ink (d1) from the rest?

    python docs/bench/edge_misfit_2026-11-28.py run SAMPLE OUT      # `hemicube validate --sample SAMPLE -o OUT`,
                                                                     # recording rows / dof / sigma^2 to OUT/misfit.npz
    python docs/bench/edge_misfit_2026-11-28.py analyse OUT [OUT...] # any validate or suite sample folder

The misfit of a texel is its sum of squared residuals at its own fit (the joint prior's start) over dof sigma^2, the
joint prior's own noise scale (the median texel's misfit is 1). The last joint prior of a run is recorded: the refit's
where there is one. Stock: true rho_s < 0.4; foil > 5; ink between. dN: the stock texel's chessboard distance to the
nearest ink or foil texel.
"""
import sys
from pathlib import Path

import numpy as np


def run(sample: str, out: str) -> None:
    import torch

    import reconstruction.fitting as F
    from hemicube.cli import main

    orig = F._joint_roughness

    def recorded(prob, q, rho_d, grid_shape, resume=None, save=None):
        with torch.no_grad():
            rows = torch.cat([F._loss(prob.part(i), q[i]) for i in F._chunks(prob, prob.config.batch)])
        x, info = orig(prob, q, rho_d, grid_shape, resume, save)
        Path(out).mkdir(parents=True, exist_ok=True)
        np.savez(Path(out) / "misfit.npz", rows=rows.double().cpu().numpy(),
                 dof=max(F._residual_count(prob) - F.GEOMETRY_SIZE, 1), sigma2=info["joint_sigma2"])
        return x, info

    F._joint_roughness = recorded
    sys.exit(main(["validate", "--sample", sample, "-o", out]))


def analyse(folder: str) -> None:
    from scipy import ndimage

    from reconstruction.metrics import RHO_FLOOR
    from reconstruction.output import ReconstructionFolder
    from reconstruction.validation import resample_maps
    from twin.capture.session import CaptureSession

    d = Path(folder)
    m = ReconstructionFolder(d / "reconstruction").maps()
    R = m.alpha.shape[0]
    t = resample_maps(CaptureSession.open(d / "capture").ground_truth_maps(), m.size_mm, R)
    stock, foil = t.rho_s.mean(-1) < 0.4, t.rho_s.mean(-1) > 5
    dist = ndimage.distance_transform_cdt(stock, metric="chessboard")
    err = np.log(m.alpha).mean(-1) - np.log(t.alpha).mean(-1)  # mean log alpha
    ex, ey = (np.abs(m.alpha[..., k] / t.alpha[..., k] - 1) for k in (0, 1))
    es = (m.rho_s - t.rho_s) / np.maximum(t.rho_s, RHO_FLOOR[1])  # per channel, signed: the metric's floor
    misfit = None
    if (d / "misfit.npz").exists():
        z = np.load(d / "misfit.npz")
        misfit = (z["rows"] / z["dof"] / z["sigma2"]).reshape(R, R)
    print(f"{folder}: alpha_x / alpha_y / rho_s medians, all texels {100 * np.median(ex):.2f} / "
          f"{100 * np.median(ey):.2f} / {100 * np.median(np.abs(es)):.2f}%")
    groups = [("ink", ~stock & ~foil), ("foil", foil)] + [
        (f"d{lo}" + ("+" if hi > 99 else f"-{hi}" if hi > lo else ""), stock & (dist >= lo) & (dist <= hi))
        for lo, hi in ((1, 1), (2, 2), (3, 4), (5, 10 ** 6))]
    for name, sel in groups:
        if not sel.any():
            continue
        line = (f"  {name:5s} n={sel.sum():4d}  log alpha error mean {err[sel].mean():+.3f} median |.| "
                f"{np.median(np.abs(err[sel])):.3f}  alpha_x / alpha_y {100 * np.median(ex[sel]):5.1f} / "
                f"{100 * np.median(ey[sel]):5.1f}%  rho_s {100 * np.median(np.abs(es[sel])):5.1f}% "
                f"(mean signed {100 * es[sel].mean():+.1f}%)")
        if misfit is not None:
            r = misfit[sel]
            line += f"  misfit p10 / median / p90 {np.percentile(r, 10):.2f} / {np.median(r):.2f} / {np.percentile(r, 90):.2f}"
        print(line)
    if misfit is not None:
        d1 = stock & (dist == 1)
        print(f"  correlation of log misfit and log alpha error on d1: {np.corrcoef(np.log(misfit[d1]), err[d1])[0, 1]:+.3f}")


if __name__ == "__main__":
    if sys.argv[1] == "run":
        run(sys.argv[2], sys.argv[3])
    else:
        for f in sys.argv[2:]:
            analyse(f)
