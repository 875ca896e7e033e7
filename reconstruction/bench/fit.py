"""`hemicube bench fit-forward` and `hemicube bench fit-jacobian`: the GGX fit's forward model and its Jacobian
(reconstruction.stages.fitting), each against the path or the derivative it replaced as the same-run baseline."""
from __future__ import annotations

import numpy as np

from reconstruction.bench.common import best_of, device_name, positive_int, synchroniser


def _random_points(rig, texels: int, seed: int, device: str):
    """Seeded synthetic texels of the fit's benches: positions over 90% of the sample, normals within ~10 deg of
    the plane's, tangents along its x axis, roughness log-uniform in [0.011, 0.37]; torch tensors on `device`."""
    import torch

    positive_int("texels", texels)
    g = torch.Generator().manual_seed(seed)
    half = 0.45 * rig.sample.max_size
    pos = torch.as_tensor(rig.sample.origin, dtype=torch.float32).repeat(texels, 1)
    pos += (torch.rand(texels, 1, generator=g) * 2 - 1) * half * torch.as_tensor(rig.sample.x_axis, dtype=torch.float32)
    pos += (torch.rand(texels, 1, generator=g) * 2 - 1) * half * torch.as_tensor(rig.sample.y_axis, dtype=torch.float32)
    n = torch.as_tensor(rig.sample.normal, dtype=torch.float32) + 0.3 * (torch.rand(texels, 3, generator=g) - 0.5)
    n = (n / n.norm(dim=1, keepdim=True)).to(device)
    t = torch.as_tensor(rig.sample.x_axis, dtype=torch.float32).repeat(texels, 1).to(device)
    ax = torch.exp(torch.rand(texels, generator=g) * 3.5 - 4.5).to(device)
    ay = torch.exp(torch.rand(texels, generator=g) * 3.5 - 4.5).to(device)
    return pos.to(device), n, t, ax, ay, g


def bench_fit_forward(rig_name="mini", device="cpu", texels=2304, repeats=5, seed=0) -> dict:
    """`hemicube bench fit-forward`: seconds of one evaluation of the forward model as the GGX fit makes it
    (reconstruction.stages.fitting.model._lumitexels: unit diffuse and specular albedo, the rig's upper LEDs, without
    gradients), against the same-run baseline of the path the fit took before: the autograd bridge's tape and
    copies (twin.optics.torch_ops.WarpForward) over all of the rig's LEDs, then the upper ones selected. The
    two must agree to the bit (rtol 0): they run the same kernel on the same numbers."""
    positive_int("repeats", repeats)
    from dataclasses import replace

    import torch

    import twin
    from twin.bench import finish_checks, same_work
    from twin.optics.torch_ops import WarpForward, _tensors

    rig = twin.load_rig(rig_name)
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    sub = replace(rig, leds=rig.leds.subset(upper))
    pos, n, t, ax, ay, _ = _random_points(rig, texels, seed, device)
    e = torch.eye(3, device=device)
    rd, rs = e[0].expand(texels, 3), e[1].expand(texels, 3)
    beta = torch.zeros(texels, device=device)
    idx = torch.as_tensor(upper, device=device)

    def fit_path():
        return twin.lumitexels(sub, pos, n, t, rd, rs, ax, ay, convention="physical", device=device,
                               camera="primary", transparency=beta, visibility=True)

    def tape_path():
        args = _tensors(pos, n, t, rd, rs, ax, ay, beta, device)
        return WarpForward.apply((rig, "physical", "primary", "separable", "schlick", 1.5, True), *args,
                                 None).index_select(1, idx)

    sync = synchroniser(device)
    seconds = {}
    with torch.no_grad():
        out = {}
        for name, fn in (("fit_path", fit_path), ("baseline_tape_all_leds", tape_path)):
            out[name] = fn().cpu().numpy()  # kernels loaded, not timed
            seconds[name] = best_of(fn, repeats, sync)
    check = same_work("fit_path_vs_tape_all_leds", out["fit_path"], out["baseline_tape_all_leds"], rtol=0.0)
    return finish_checks({"bench": "fit-forward", "rig": rig.name, "leds_upper": int(upper.size),
                          "leds_all": rig.num_leds, "texels": texels, "repeats": repeats,
                          "device": device_name(device),
                          "seconds": seconds, "speedup": seconds["baseline_tape_all_leds"] / seconds["fit_path"]},
                         [check])


# `hemicube bench fit-jacobian`'s check. The timed baseline, forward differences of step h = FitConfig.fd_step = 1e-3,
# differs from the exact derivative by its truncation error, O(h) relative where the residuals vary slowly and far
# more across a narrow lobe (0.06 deg of normal against a 0.6-deg lobe): a median 4e-3 on the mini rig, not a bound
# to check against. Central differences of the same step (not timed) err by O(h^2) plus float32 rounding (measured
# median 5e-4): the analytic Jacobian's median relative difference to them must stay <= 2e-3, which a 1% error of
# the analytic one exceeds five times (tests/hemicube/test_bench.py).
JACOBIAN_MEDIAN_BOUND = 2e-3
# The fit's Gauss-Newton system (J J^T, J r) summed in Warp (reconstruction.stages.fitting.sums) against the products
# of the stored Jacobian: the same float32 numbers summed in another order, ~1e-6 relative apart
# (tests/reconstruction/test_fit_sums.py: 1e-12 in float64); a wrong row or factor is off by far more than the bound.
NORMAL_EQUATIONS_BOUND = 1e-4


def bench_fit_jacobian(rig_name="mini", device="cpu", texels=2304, repeats=3, seed=0) -> dict:
    """`hemicube bench fit-jacobian`: seconds of one Jacobian of the GGX fit's residuals (reconstruction.stages.fitting:
    the lumitexels and both views' photos under the linear lights, albedos in closed form) at a perturbed geometry,
    analytic (FitConfig.jacobian "analytic": twin.optics.jvp and variable projection) against the same-run
    baseline of forward differences ("forward", five more evaluations of the residuals), and one evaluation of the
    residuals. Also timed: what the fit takes instead of the stored Jacobian, its Gauss-Newton system summed in Warp
    (fitting.jacobian._normal_equations), and the loss alone (fitting.model._loss). The checks: per texel and number,
    |J_analytic - J_central| / |J_central| over the residuals for central differences of the same step, its median
    <= JACOBIAN_MEDIAN_BOUND (the forward differences' difference is reported beside it); and the system's J J^T
    and J r against those of the stored analytic Jacobian, per texel, their median relative difference <=
    NORMAL_EQUATIONS_BOUND."""
    positive_int("repeats", repeats)
    from dataclasses import replace

    import torch

    import twin
    from twin.capture.pattern_sets import linear_lights

    from reconstruction.stages.fitting import FitConfig, jacobian, model
    from reconstruction.stages.fitting.config import GEOMETRY_SIZE
    from reconstruction.stages.fitting.problem import _problem
    from reconstruction.network.data import LUMITEXEL_SCALE

    rig = twin.load_rig(rig_name)
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    sub = replace(rig, leds=rig.leds.subset(upper))
    pos, n, t, ax, ay, g = _random_points(rig, texels, seed, device)
    rd = (0.05 + 0.7 * torch.rand(texels, 3, generator=g)).to(device)
    rs = (0.1 + 2.0 * torch.rand(texels, 3, generator=g)).to(device)
    W = torch.as_tensor(linear_lights(rig).weights[:, upper], dtype=torch.float32, device=device)
    kw = dict(convention="physical", device=device, visibility=True)
    with torch.no_grad():
        lumi = twin.lumitexels(sub, pos, n, t, rd, rs, ax, ay, camera="primary", **kw) * LUMITEXEL_SCALE
        views = [twin.measurements(sub, pos, n, t, rd, rs, ax, ay, W, camera=c, **kw) * LUMITEXEL_SCALE
                 for c in ("primary", "secondary")]
        config = FitConfig(device=device)
        prob = _problem(rig, pos, lumi, views[0], W, None, config, secondary=(views[1], W))
        N, X, Y = (torch.as_tensor(v, dtype=torch.float32, device=device)
                   for v in (rig.sample.normal, rig.sample.x_axis, rig.sample.y_axis))
        c = n @ N
        q = torch.stack([n @ X / c, n @ Y / c, torch.full_like(c, 0.3), torch.log(ax) + 0.2, torch.log(ay) - 0.2], 1)
        r = model._residuals(prob, q)
        sync = synchroniser(device)
        seconds, out = {}, {}
        for name, fn in (("analytic", lambda: jacobian._analytic_jacobian(prob, q)),
                         ("baseline_forward_difference", lambda: jacobian._forward_difference(prob, q, r)),
                         ("residuals", lambda: model._residuals(prob, q)),
                         ("normal_equations", lambda: jacobian._normal_equations(prob, q)),
                         ("loss", lambda: model._loss(prob, q))):
            out[name] = fn()  # kernels loaded, not timed
            seconds[name] = best_of(fn, repeats, sync)
        h = config.fd_step
        eye = torch.eye(GEOMETRY_SIZE, device=q.device) * h
        central = torch.stack([(model._residuals(prob, q + eye[j]) - model._residuals(prob, q - eye[j])) / (2 * h)
                               for j in range(GEOMETRY_SIZE)], 1)
    Ja = out["analytic"].double()

    def rel(J):
        J = J.double()
        return ((Ja - J).norm(dim=2) / J.norm(dim=2).clamp_min(1e-30)).cpu().numpy()

    rc, rf = rel(central), rel(out["baseline_forward_difference"])
    med = float(np.median(rc))
    check = {"check": "analytic_vs_central_difference_jacobian", "median_rel_diff": med,
             "p90_rel_diff": float(np.quantile(rc, 0.9)), "bound": JACOBIAN_MEDIAN_BOUND,
             "forward_difference_median_rel_diff": float(np.median(rf)),
             "forward_difference_p90_rel_diff": float(np.quantile(rf, 0.9)),
             "passed": bool(np.isfinite(Ja.cpu().numpy()).all() and med <= JACOBIAN_MEDIAN_BOUND)}
    A, g, _ = (x.double() for x in out["normal_equations"])
    A_ref, g_ref = Ja @ Ja.transpose(1, 2), (Ja @ r.double()[..., None])[..., 0]
    eA = ((A - A_ref).flatten(1).norm(dim=1) / A_ref.flatten(1).norm(dim=1).clamp_min(1e-30)).cpu().numpy()
    eg = ((g - g_ref).norm(dim=1) / g_ref.norm(dim=1).clamp_min(1e-30)).cpu().numpy()
    medA, medg = float(np.median(eA)), float(np.median(eg))
    system = {"check": "normal_equations_vs_stored_jacobian", "median_rel_diff_JJt": medA,
              "median_rel_diff_Jr": medg, "bound": NORMAL_EQUATIONS_BOUND,
              "passed": bool(np.isfinite(eA).all() and max(medA, medg) <= NORMAL_EQUATIONS_BOUND)}
    from twin.bench import finish_checks

    return finish_checks({"bench": "fit-jacobian", "rig": rig.name, "leds_upper": int(upper.size), "texels": texels,
                          "residuals_per_texel": int(r.shape[1]), "repeats": repeats,
                          "device": device_name(device),
                          "seconds": seconds,
                          "speedup": seconds["baseline_forward_difference"] / seconds["analytic"]}, [check, system])
