"""Measurement extraction (reference §6.1, §6.3), decode and the calibrations it applies.

Oracle: the exact measurements of the TRUE maps at the texel centres, rendered by the forward model and
projected by the network's own pattern layer. The photos carry sensor noise (shot, read, quantisation), an
HDR merge and a pixel footprint of ~1 mm against 2.2 mm texels, so agreement is statistical: median
relative errors (per texel, relative to its largest |measurement|) are bounded at 2% (measured 0.5-0.6%).
"""
from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch

import twin
from twin.camera.correction import apply_colour_matrix, colour_matrix, flat_field
from twin.capture.plan import CaptureError
from twin.capture.session import CaptureSession
from reconstruction.data import synthesize
from reconstruction.extraction import (ExtractionError, GRID_SHRINK, TextureGrid, corrected, detect_sample_size,
                                       extract, texture_grid)
from reconstruction.latents import check_patterns, decode, read_latent_exr, write_latent_exr
from reconstruction.pretrained import load_pretrained
from twin.camera.sensor import apply_optics


class _ExactAlignment:
    """The true primary -> secondary pixel map of the sample plane (from both calibrations): isolates the
    extraction from the alignment, which tests/test_alignment.py scores on its own."""

    def __init__(self, rig):
        c0, c1 = rig.camera("primary"), rig.camera("secondary")
        ys, xs = np.mgrid[0:c0.height, 0:c0.width]
        hits = c0.plane_points(np.stack([xs.ravel(), ys.ravel()], 1).astype(float), rig.sample.origin,
                               rig.sample.normal)
        self.map = c1.project(hits)[0].reshape(c0.height, c0.width, 2).astype(np.float32)


@pytest.fixture(scope="module")
def extracted(validate_dir, mini):
    cap = CaptureSession.open(validate_dir / "capture")
    grid = texture_grid(cap, mini, 32)
    return cap, grid, extract(cap, mini, grid, _ExactAlignment(mini))


def _true_params(cap, rig, grid):
    from twin.camera.imaging import _bilinear
    from twin.materials.samples import world_to_texel

    gt = cap.ground_truth_maps()
    pos = grid.positions(rig)
    rc = world_to_texel(gt, rig.sample, pos)
    b = _bilinear(gt, rc[:, 0], rc[:, 1])
    n = b["normal"] / np.linalg.norm(b["normal"], axis=1, keepdims=True)
    t = b["tangent"] - (b["tangent"] * n).sum(1, keepdims=True) * n
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    f = np.float32
    return dict(position=pos.astype(f), normal=n.astype(f), tangent=t.astype(f), rho_d=b["rho_d"].astype(f),
                rho_s=b["rho_s"].astype(f), alpha_x=b["alpha"][:, 0].astype(f), alpha_y=b["alpha"][:, 1].astype(f)), \
        b["transparency"][:, 0]


def test_texture_grid_covers_the_sample(extracted, mini):
    """ramps is 120 mm wide: the detected square is 120 mm within a pixel (~1 mm), then shrunk by 6.5% a side."""
    cap, grid, meas = extracted
    assert detect_sample_size(cap, mini) == pytest.approx(120.0, abs=2.0)
    assert grid.size_mm == pytest.approx(detect_sample_size(cap, mini) * (1 - 2 * GRID_SHRINK))
    assert meas.valid.all() and meas.learned.shape == (32 * 32, 2, 32) and meas.lines.shape == (32 * 32, 64, 3)
    assert texture_grid(cap, mini, 16, size_mm=50.0) == TextureGrid(16, 50.0)


def test_learned_measurements_match_the_true_maps(extracted, mini):
    cap, grid, meas = extracted
    model, _ = load_pretrained("mini")
    p, _ = _true_params(cap, mini, grid)
    views = torch.stack([synthesize(mini, p, "primary"), synthesize(mini, p, "secondary")], dim=1)
    with torch.no_grad():
        exact = model.measure(views).numpy()
    rel = np.abs(meas.learned - exact) / np.abs(exact).max(axis=2, keepdims=True)
    assert np.median(rel[:, 0]) < 0.02 and np.median(rel[:, 1]) < 0.02, np.median(rel, axis=(0, 2))


def test_line_measurements_and_transparency_match_the_true_maps(extracted, mini):
    from reconstruction.data import LUMITEXEL_SCALE

    cap, grid, meas = extracted
    p, beta = _true_params(cap, mini, grid)
    w = np.zeros((64, mini.num_leds, 3), np.float32)
    w[:, ~mini.is_bottom] = meas.line_weights
    exact = twin.measurements(mini, **p, patterns=w, transparency=np.zeros(len(meas.valid)), camera="primary",
                              visibility=True) * LUMITEXEL_SCALE
    rel = np.abs(meas.lines - exact) / np.abs(exact).max(axis=(1, 2), keepdims=True)
    assert np.median(rel) < 0.02, np.median(rel)
    # ramps has a beta ramp in one region, opaque elsewhere; texels straddling the ramp's steps mix values
    err = np.abs(meas.transparency - beta)
    assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.1, (np.median(err), np.percentile(err, 95))


def test_decode_and_latent_exr(extracted, tmp_path):
    cap, grid, meas = extracted
    model, _ = load_pretrained("mini")
    check_patterns(model, cap, twin.load_rig("mini"))
    z = decode(model, meas.learned, batch=100)
    assert z.shape == (len(meas.learned), 56) and np.isfinite(z).all()
    np.testing.assert_array_equal(z, decode(model, meas.learned))  # batching changes nothing (eval mode)
    write_latent_exr(tmp_path / "latent.exr", np.repeat(z, 2, axis=1)[:, :72], grid.shape)
    np.testing.assert_array_equal(read_latent_exr(tmp_path / "latent.exr").reshape(-1, 72),
                                  np.repeat(z, 2, axis=1)[:, :72])
    with pytest.raises(ValueError, match="NaN"):
        decode(model, np.full_like(meas.learned, np.nan))


def test_calibrations_undo_the_optics(mini):
    """A camera with crosstalk and vignetting: flat field and colour matrix give back the LED-RGB radiance."""
    cam = mini.camera("primary")
    sensor = dataclasses.replace(cam.sensor, vignetting=(-0.3, 0.05, 0.0),
                                 crosstalk=((0.9, 0.08, 0.02), (0.1, 0.8, 0.1), (0.01, 0.12, 0.87)))
    cam = dataclasses.replace(cam, sensor=sensor)
    x = np.random.default_rng(0).uniform(0, 2, (cam.height, cam.width, 3)).astype(np.float32)
    np.testing.assert_allclose(corrected(apply_optics(x, cam), cam), x, rtol=1e-5, atol=1e-6)
    assert flat_field(cam).max() > 1.2  # the corners are brightened
    np.testing.assert_allclose(apply_colour_matrix(x @ np.asarray(sensor.crosstalk, np.float32).T,
                                                   colour_matrix(cam)), x, rtol=1e-5, atol=1e-6)
    singular = dataclasses.replace(cam, sensor=dataclasses.replace(sensor, crosstalk=((1, 1, 0), (1, 1, 0), (0, 0, 1))))
    with pytest.raises(ValueError, match="ill-conditioned"):
        colour_matrix(singular)


def test_bad_captures_are_refused(extracted, mini, tmp_path):
    cap, grid, _ = extracted
    from reconstruction.pipeline import reconstruct

    with pytest.raises(CaptureError, match="not a capture folder"):
        reconstruct(tmp_path, tmp_path / "recon", progress=False)
    broken = tmp_path / "broken"
    shutil.copytree(cap.dir, broken, ignore=shutil.ignore_patterns("raw", "ground_truth", ".lock"))
    (broken / "img00070_cam00.exr").unlink()
    with pytest.raises(CaptureError, match="img00070_cam00.exr: listed in the manifest but missing"):
        extract(CaptureSession.open(broken), mini, grid, _ExactAlignment(mini))
    out = tmp_path / "recon"
    with pytest.raises(CaptureError, match="img00070_cam00.exr: listed in the manifest but missing"):
        reconstruct(broken, out, progress=False)
    # no partial or temporary folder; only the finished stages, kept for a resumed run (reconstruction.output)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".recon.stages", "broken"]
    import json

    assert sorted(json.loads((tmp_path / ".recon.stages" / "stages.json").read_text())) == ["alignment"]

    from twin.atomic import file_sha256
    from twin.materials.exr import read_rgb_exr, write_rgb_exr

    # a device that wrote NaN (and checksummed it): the photo verifies, its values are refused
    img = read_rgb_exr(broken / "img00000_cam00.exr")
    img[3, 4, 1] = np.nan
    write_rgb_exr(broken / "img00000_cam00.exr", img)
    doc = json.loads((broken / "manifest.json").read_text())
    doc["files"]["img00000_cam00.exr"] = file_sha256(broken / "img00000_cam00.exr")
    (broken / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match="NaN or Inf"):
        extract(CaptureSession.open(broken), mini, grid, _ExactAlignment(mini))
    with pytest.raises(ExtractionError, match="another rig"):
        extract(cap, twin.load_rig("paper"), grid, _ExactAlignment(mini))
    with pytest.raises(ExtractionError, match="grid resolution"):
        TextureGrid(1, 10.0)
