"""The bench commands check that their same-run baseline computes the same thing: a matching baseline
passes (exit 0), a deliberately drifted one fails (exit 1). Tiny sizes: the figures are not the point."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hemicube.cli import main


def _run(argv, capsys):
    rc = main(argv)
    out = capsys.readouterr()
    return rc, json.loads(out.out), out.err


LUMI = ["bench", "lumitexel", "--rig", "mini", "--points", "16", "--repeats", "1", "--no-compile"]


@pytest.mark.slow
def test_bench_lumitexel_baseline_matches(capsys):
    rc, res, _ = _run(LUMI, capsys)
    assert rc == 0 and res["passed"]
    assert {c["check"] for c in res["checks"]} == {"warp_fused_vs_torch_eager",
                                                   "warp_materialise_projected_vs_torch_eager",
                                                   "warp_materialise_fast_projected_tf32_vs_torch_eager",
                                                   "projection_tf32_vs_float64"}


def test_bench_lumitexel_drifted_baseline_fails(capsys, monkeypatch):
    import twin.bench

    plain = twin.bench.torch_lumitexel
    # a drift on one side only: the baseline loses 1 % of the LED intensity
    monkeypatch.setattr(twin.bench, "torch_lumitexel", lambda *a: plain(*a) * 0.99)
    rc, res, err = _run(LUMI, capsys)
    assert rc == 1 and not res["passed"]
    assert "warp_fused_vs_torch_eager" in err and "warp_materialise_fast_projected_tf32_vs_torch_eager" in err


RECON = ["bench", "reconstruct", "--rig", "mini", "--texels", "8"]


@pytest.mark.slow
def test_bench_reconstruct_baseline_matches_and_drift_fails(capsys, monkeypatch):
    rc, res, _ = _run(RECON, capsys)
    assert rc == 0 and res["passed"]
    assert [c["check"] for c in res["checks"]] == ["finetune_batch100_vs_batched_lines_few_steps",
                                                   "finetune_default_vs_float32_median_objective",
                                                   "fitting_default_vs_float32_median_loss"]
    assert res["finetune_precision"] == "tf32" and res["finetune_float32"]["seconds"] > 0
    assert res["fit_precision"] == "tf32" and res["fitting_float32"]["seconds"] > 0
    # on the CPU every product is float32: the two fits are the same computation
    assert res["median_texel_loss"]["fitting"] == res["median_texel_loss"]["fitting_float32"]
    import reconstruction.stages.finetune as ft
    import reconstruction.stages.fitting as fitting

    plain = ft.finetune

    def drifted(model, latent, *a, **kw):  # the batched baseline starts from a shifted latent
        cfg = a[-1] if a else kw["config"]
        return plain(model, latent + (0.5 if cfg.batch == 100 else 0.0), *a, **kw)

    monkeypatch.setattr(ft, "finetune", drifted)
    rc, res, err = _run(RECON, capsys)
    assert rc == 1 and "finetune_batch100_vs_batched_lines" in err

    def worse(model, latent, *a, **kw):  # the default precision's run ends further from the photos than float32's
        cfg = a[-1] if a else kw["config"]
        r = plain(model, latent, *a, **kw)
        if cfg.precision != "float32" and cfg.source == "code":
            r.latent = r.latent + 0.5
        return r

    plain_fit = fitting.fit_ggx

    def worse_fit(*a, config, **kw):  # and the default precision's fit ends 5% above float32's
        r = plain_fit(*a, config=config, **kw)
        if config.precision != "float32":
            r.info["texel_loss"] = r.info["texel_loss"] * 1.05
        return r

    monkeypatch.setattr(ft, "finetune", worse)
    monkeypatch.setattr(fitting, "fit_ggx", worse_fit)
    rc, res, err = _run(RECON, capsys)
    assert rc == 1 and "finetune_default_vs_float32_median_objective" in err
    assert "fitting_default_vs_float32_median_loss" in err


FIT = ["bench", "fit-forward", "--rig", "mini", "--texels", "32", "--repeats", "1"]


def test_bench_fit_forward_baseline_matches_to_the_bit_and_drift_fails(capsys, monkeypatch):
    rc, res, _ = _run(FIT, capsys)
    assert rc == 0 and res["passed"] and res["leds_upper"] < res["leds_all"]
    assert res["checks"][0]["check"] == "fit_path_vs_tape_all_leds" and res["checks"][0]["max_rel_diff"] == 0.0
    import twin.optics.torch_ops as ops

    plain = ops.WarpForward.apply
    monkeypatch.setattr(ops.WarpForward, "apply", lambda *a: plain(*a) * (1 + 1e-6))  # one float32 ulp off
    rc, res, err = _run(FIT, capsys)
    assert rc == 1 and "fit_path_vs_tape_all_leds" in err


JAC = ["bench", "fit-jacobian", "--rig", "mini", "--texels", "64", "--repeats", "1"]


@pytest.mark.slow
def test_bench_fit_jacobian_checks_the_analytic_one_and_a_one_percent_error_fails(capsys, monkeypatch):
    rc, res, _ = _run(JAC, capsys)
    assert rc == 0 and res["passed"] and set(res["seconds"]) == {"analytic", "baseline_forward_difference",
                                                                  "residuals", "normal_equations", "loss"}
    c, system = res["checks"]
    assert c["check"] == "analytic_vs_central_difference_jacobian" and c["median_rel_diff"] < c["bound"]
    assert c["forward_difference_median_rel_diff"] > c["median_rel_diff"]  # the baseline's truncation, reported
    assert system["check"] == "normal_equations_vs_stored_jacobian"
    assert max(system["median_rel_diff_JJt"], system["median_rel_diff_Jr"]) < system["bound"] / 10
    import reconstruction.stages.fitting.jacobian as F

    plain = F._analytic_jacobian
    monkeypatch.setattr(F, "_analytic_jacobian", lambda *a: plain(*a) * 1.01)
    rc, res, err = _run(JAC, capsys)
    assert rc == 1 and "analytic_vs_central_difference_jacobian" in err


@pytest.mark.slow
def test_bench_fit_jacobian_fails_a_normal_equations_one_row_off(capsys, monkeypatch):
    """The Warp-summed system (fitting.jacobian._normal_equations) against the stored Jacobian's: its J r off by 1%
    fails the check."""
    import reconstruction.stages.fitting.jacobian as F

    plain = F._normal_equations
    monkeypatch.setattr(F, "_normal_equations", lambda *a: (lambda A, g, e: (A, g * 1.01, e))(*plain(*a)))
    rc, res, err = _run(JAC, capsys)
    assert rc == 1 and "normal_equations_vs_stored_jacobian" in err


@pytest.mark.parametrize("argv, message", [(["--repeats", "0"], "repeats must be a positive integer"),
                                           (["--texels", "0"], "texels must be a positive integer")])
@pytest.mark.parametrize("bench", ["fit-forward", "fit-jacobian"])
def test_fit_benches_refuse_bad_counts_before_any_work(bench, argv, message, capsys):
    assert main(["bench", bench, "--rig", "mini", *argv]) == 2
    assert message in capsys.readouterr().err


CAPTURE = ["bench", "capture", "--rig", "mini", "--device", "cpu", "--sample-resolution", "32", "--scale", "0.5"]


@pytest.mark.slow
def test_bench_capture_whole_plan_and_checks(capsys, monkeypatch):
    rc, res, _ = _run(CAPTURE, capsys)
    assert rc == 0 and res["passed"] and res["photos"] == 196
    assert {"warmup", "trace", "render", "sensor", "hdr", "download"} <= set(res["seconds"])
    names = {c["check"] for c in res["checks"]}
    assert {"render_sample_primary", "render_sample_secondary", "render_empty_primary",
            "hdr_merge_first_photo"} <= names
    import twin.camera.imaging as imaging

    plain = imaging.render_reference
    monkeypatch.setattr(imaging, "render_reference", lambda *a, **kw: plain(*a, **kw) * np.float32(1.001))
    rc, res, err = _run(CAPTURE, capsys)
    assert rc == 1 and "render_sample_primary" in err


def test_untrained_bench_network_gets_the_measurements_batch_statistics():
    """`bench reconstruct` without a trained network gives the untrained encoder the BatchNorm statistics of the
    bench's own measurements (else its fine-tuning overflows on the paper rig): each BatchNorm's running mean and
    variance become the mean and unbiased variance of its input over those measurements, weights untouched."""
    import torch

    import twin
    from reconstruction.bench.reconstruct import _normalise_encoder
    from reconstruction.stages.latents import decode
    from reconstruction.network.architecture import AcquisitionNet
    from reconstruction.network.train import TrainConfig

    rig = twin.load_rig("mini")
    torch.manual_seed(0)
    model = AcquisitionNet(TrainConfig().network_config(int((~np.asarray(rig.is_bottom)).sum()))).eval()
    weights = {k: v.clone() for k, v in model.state_dict().items() if "running" not in k and "num_batches" not in k}
    learned = (torch.rand(300, 2, 32, generator=torch.Generator().manual_seed(1)) * 500).numpy()
    _normalise_encoder(model, learned, "cpu")
    first = model.encoder.albedo_branch
    with torch.no_grad():
        pre = first[0](torch.from_numpy(learned).reshape(300, -1))
    assert torch.allclose(first[1].running_mean, pre.mean(0), rtol=1e-4, atol=1e-4)
    assert torch.allclose(first[1].running_var, pre.var(0, unbiased=True), rtol=1e-4)
    assert not model.training and first[1].momentum == 0.1
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in weights.items())
    z = decode(model, learned)
    assert np.isfinite(z).all() and np.abs(z).max() < 100
