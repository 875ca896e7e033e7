"""Scoring a reconstruction against the twin's ground truth (docs/accuracy.md).

    metrics, panels = evaluate(capture, recon, rig)
    checks = check(metrics, THRESHOLDS["mini"])            # reconstruction.evaluation.metrics
    write_report(out, title=..., metrics=metrics, checks=checks, panels=panels, notes=...)

What is compared
* **alignment**: the alignment map against the capture's pixel <-> texel sidecars (secondary pixels);
* **maps**: the fitted maps against the true maps resampled onto the reconstruction's texture grid
  (normal and tangent angles, |log alpha|, relative rho_d and rho_s; reconstruction.evaluation.metrics.map_errors);
* **renders under the held-out line** (the photo left out of fine-tuning), on the texture grid:
  the photo's texel values against (a) the latent render (decoder x line pattern, reference §6.4's
  "latent" image), (b) the fitted maps rendered by the forward model, and (c) the TRUE maps rendered the
  same way, (c) being the ceiling the photo's noise and the pixel footprint allow. SSIM and PSNR;
* **novel views and lights**: the fitted maps against the truth under 560 pairs of view and light the capture never
  used (reconstruction.evaluation.novel_views, the paper's Fig. 14).
"""
from __future__ import annotations

import time

import numpy as np

from reconstruction.evaluation.metrics import Threshold, image_scores, map_errors, resample_maps, truth_coverage
from reconstruction.evaluation.report import FigurePanel, Panel, RenderPanel, map_panels

# The novel views' goals (this project's, for synthetic data; stricter than the paper's real-data means of
# 0.90-0.97, §10.2): every configuration, the default's included, is held to them.
NOVEL_GOALS = [
    Threshold("novel.ssim.mean", ">=", 0.97, "goal: mean SSIM over 560 novel view/light pairs"),
    Threshold("novel.ssim.worst", ">=", 0.90, "goal: the worst of the 560 pairs"),
]

# Thresholds of the CI configuration (mini rig, ramps, seed 1, 48^2 texels, the shipped mini network), set
# once from its measured values (in brackets) with a stated margin, and not to be loosened to
# pass: error medians at 2-4x what was measured (run-to-run and machine-to-machine spread is far smaller;
# the margin is for honest algorithmic changes), SSIM/PSNR a few points below. docs/accuracy.md has the table.
THRESHOLDS = {
    "mini": [
        Threshold("alignment.median_px", "<=", 0.5, "the alignment goal (measured 0.13 px)"),
        Threshold("maps.normal_deg.median", "<=", 0.25, "measured 0.06 deg"),
        Threshold("maps.tangent_deg.median", "<=", 2.0, "measured 0.41 deg where alpha_x/alpha_y >= 1.5"),
        Threshold("maps.alpha_x_pct.median", "<=", 8.0, "measured 2.3%; the paper-rig goal is 10%"),
        Threshold("maps.alpha_y_pct.median", "<=", 8.0, "measured 1.6%"),
        Threshold("maps.rho_d_pct.median", "<=", 1.5, "measured 0.30%"),
        Threshold("maps.rho_s_pct.median", "<=", 5.0, "measured 1.3%"),
        Threshold("maps.transparency_abs.median", "<=", 0.02, "measured < 1e-5 (opaque texels dominate)"),
        Threshold("render.maps.ssim", ">=", 0.93, "measured 0.959 (true maps: 0.963)"),
        Threshold("render.maps.psnr_db", ">=", 32.0, "measured 35.7 dB"),
        Threshold("render.latent.ssim", ">=", 0.70, "measured 0.753: the mini network's decoder limits it"),
        *NOVEL_GOALS,
    ],
}


def _render_lines(rig, positions, params: dict, pattern: np.ndarray, device) -> np.ndarray:
    """(N, 3) line measurements in network units of texels with params under one line pattern (L_upper, 3)."""
    w = np.zeros((1, rig.num_leds, 3), np.float32)
    w[0, np.flatnonzero(~np.asarray(rig.is_bottom))] = pattern
    return exact_measurements(rig, positions, params, w, next(iter(rig.cameras)), device)[:, 0]


def exact_measurements(rig, positions, params: dict, patterns, camera, device) -> np.ndarray:
    """(N, K, 3) measurements of `patterns` (K, num_leds, 3) in `camera`'s view, exact (twin.measurements in the
    physical convention the capture renders in, an opaque sample; no camera pixels, no noise), in network units."""
    import twin

    from reconstruction.network.data import LUMITEXEL_SCALE

    m = twin.measurements(rig, positions.astype(np.float32), patterns=patterns, transparency=np.zeros(len(positions)),
                          convention="physical", camera=camera, visibility=True, device=device, **params)
    return m * np.float32(LUMITEXEL_SCALE)


def map_parameters(maps) -> dict:
    """The GGX parameters of OpenSVBRDF maps as the forward model takes them (twin.lumitexels' keywords), one row
    a texel."""
    return dict(normal=maps.normal.reshape(-1, 3), tangent=maps.tangent.reshape(-1, 3),
                rho_d=maps.rho_d.reshape(-1, 3), rho_s=maps.rho_s.reshape(-1, 3),
                alpha_x=maps.alpha[..., 0].reshape(-1), alpha_y=maps.alpha[..., 1].reshape(-1))


def evaluate(capture, recon, rig, device="cpu") -> tuple[dict, list]:
    """(metrics, panels) of a reconstruction of a twin capture (which carries its ground truth): `recon` the
    Reconstruction that reconstruction.reconstruct returned for the capture folder `capture`, `rig` its rig, `device`
    where the forward model renders ("cpu", "cuda").

    metrics   grid ({resolution: texels a side, size_mm, texel_mm}), holdout_line, timings_s (seconds a stage);
              alignment (reconstruction.stages.alignment.alignment_error: median_px ... in secondary pixels);
              maps (map_errors against the truth resampled onto the grid: degrees, %, absolute);
              render ({latent, maps, truth_maps}: image_scores of each render of the held-out line against its
              photo, SSIM in [0, 1] and PSNR in dB); novel (novel_view_scores)
    panels    the report's pictures (reconstruction.evaluation.report) for write_report
    Check the metrics against thresholds_for(rig.name) with reconstruction.evaluation.metrics.check."""
    from twin.capture.session import CaptureSession

    from reconstruction.stages.alignment import alignment_error
    from reconstruction.stages.finetune import simulate_lines

    session = CaptureSession.open(capture)
    true_maps = session.ground_truth_maps()
    grid, meas, k = recon.grid, recon.measurements, recon.holdout_line
    R = grid.resolution
    metrics: dict = {"grid": {"resolution": R, "size_mm": grid.size_mm, "texel_mm": grid.texel_mm},
                     "holdout_line": k, "timings_s": dict(recon.timings)}

    metrics["alignment"] = alignment_error(recon.alignment, session.pixel_texel(0), session.pixel_texel(1))
    if "check" in recon.alignment.info:  # the check a real capture runs (no ground truth), beside the truth's figure
        metrics["alignment"]["check"] = recon.alignment.info["check"]

    truth = resample_maps(true_maps, grid.size_mm, R)
    on_sample = truth_coverage(true_maps, grid.size_mm, R)
    metrics["maps"] = map_errors(truth, recon.maps, mask=on_sample)

    pos = grid.positions(rig)
    W = meas.line_weights[k]
    photo = meas.lines[:, k].reshape(R, R, 3)
    latent = simulate_lines(recon.model, recon.latent, meas.line_weights[k:k + 1])[:, 0].reshape(R, R, 3)
    fitted = _render_lines(rig, pos, map_parameters(recon.maps), W, device).reshape(R, R, 3)
    true = _render_lines(rig, pos, map_parameters(truth), W, device).reshape(R, R, 3)
    metrics["render"] = {"latent": image_scores(photo, latent), "maps": image_scores(photo, fitted),
                         "truth_maps": image_scores(photo, true)}

    novel, novel_panels = _novel_views(rig, true_maps, recon.maps, on_sample, device)
    metrics["novel"] = novel

    panels = [RenderPanel(f"heldout_line_{k:02d}", photo, latent, fitted, origin="lower",
                          caption=f"held-out line {k} on the texture grid: photo | latent render | map render"),
              RenderPanel(f"heldout_line_{k:02d}_truth", photo, latent, true, origin="lower",
                          caption="the same photo against the TRUE maps rendered (the noise/footprint ceiling)")]
    return metrics, panels + novel_panels + map_panels(truth, recon.maps, mask=on_sample)


def _novel_views(rig, true_maps, maps, on_sample, device) -> tuple[dict, list]:
    """The novel views' scores (reconstruction.evaluation.novel_views) and their two pictures: SSIM over the
    view and light directions, and the worst pair (truth | reconstruction | difference)."""
    from reconstruction.evaluation.novel_views import directions_figure, novel_view_scores, validation_set

    t0 = time.perf_counter()
    vset = validation_set(rig)
    scores = novel_view_scores(vset, true_maps, maps, mask=on_sample, device=device, images=True)
    scores["seconds"] = time.perf_counter() - t0
    truth_img, recon_img = scores.pop("worst_images")
    ssim = np.array([p["ssim"] for p in scores["pairs"]]).reshape(len(vset.views), len(vset.lights))
    w = scores["worst"]
    return scores, [
        FigurePanel("novel_views", lambda path: directions_figure(vset, ssim, path),
                    caption="SSIM of the 560 novel view/light pairs: one unfolded cube per view (cyan: the view's "
                            "direction), each light's LEDs in its pair's colour"),
        Panel("novel_worst", truth_img, recon_img, "rgb",
              caption=f"the worst pair (SSIM {w['ssim']:.3f}): view {w['view']} (zenith / azimuth "
                      f"{w['view_angles']['zenith_deg']:.0f}° / {w['view_angles']['azimuth_deg']:.0f}°), light "
                      f"{w['light']} ({w['light_angles']['zenith_deg']:.0f}° / "
                      f"{w['light_angles']['azimuth_deg']:.0f}°): truth | reconstruction | |difference|")]


# The goals every sample must meet (docs/accuracy.md), whatever the sample, set from the goals (the paper's Fig. 13
# "almost exactly" and this project's targets), not from any sample's measured value. They apply at every
# texture-grid resolution: a grid the pipeline cannot reach them at fails, honestly. The paper rig is held to
# the same ones and to the paper's SSIM of 0.98 on real data (§10.1) for the latent render
# against the held-out photo.
_GOALS = [
    Threshold("alignment.median_px", "<=", 0.5, "goal: half a pixel"),
    Threshold("maps.normal_deg.median", "<=", 1.0, "goal"),
    Threshold("maps.tangent_deg.median", "<=", 5.0, "goal, where alpha_x/alpha_y >= 1.5",
              applies_if="maps.tangent_deg.count"),
    Threshold("maps.alpha_x_pct.median", "<=", 10.0, "goal"),
    Threshold("maps.alpha_y_pct.median", "<=", 10.0, "goal"),
    Threshold("maps.rho_d_pct.median", "<=", 3.0, "goal"),
    Threshold("maps.rho_s_pct.median", "<=", 10.0, "goal"),
    Threshold("render.maps.ssim", ">=", 0.93, "goal: fitted maps render the held-out photo"),
    *NOVEL_GOALS,
]
GOALS = {"mini": _GOALS,
         "paper": _GOALS + [Threshold("render.latent.ssim", ">=", 0.98, "goal: the paper's SSIM 0.98 (§10.1)")]}
DEFAULT_SAMPLE = "ramps"


def thresholds_for(rig_name: str, resolution: int | None = None, sample: str = DEFAULT_SAMPLE) -> list[Threshold]:
    """The thresholds a validation run is held to: the default configuration (`sample` ramps on the default
    grid) keeps THRESHOLDS, set from it; every other sample or grid resolution gets the rig's GOALS. A rig with
    neither has none (said so in the report)."""
    from reconstruction.pipeline import ReconstructConfig

    default_grid = resolution in (None, ReconstructConfig.resolution)
    if sample == DEFAULT_SAMPLE and default_grid and rig_name in THRESHOLDS:
        return list(THRESHOLDS[rig_name])
    return list(GOALS.get(rig_name, []))
