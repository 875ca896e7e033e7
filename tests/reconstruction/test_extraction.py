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
from reconstruction.network.data import synthesize
from reconstruction.stages.extraction import (ExtractionError, GRID_SHRINK, TextureGrid, corrected, detect_sample_size,
                                       extract, texture_grid)
from reconstruction.stages.latents import check_patterns, decode, read_latent_exr, write_latent_exr
from reconstruction.network.shipped import load_pretrained
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


@pytest.mark.slow
def test_texture_grid_covers_the_sample(extracted, mini):
    """ramps is 120 mm wide: the detected square is 120 mm within a pixel (~1 mm), then shrunk by 6.5% a side."""
    cap, grid, meas = extracted
    assert detect_sample_size(cap, mini) == pytest.approx(120.0, abs=2.0)
    assert grid.size_mm == pytest.approx(detect_sample_size(cap, mini) * (1 - 2 * GRID_SHRINK))
    assert meas.valid.all() and meas.learned.shape == (32 * 32, 2, 32) and meas.lines.shape == (32 * 32, 64, 3)
    assert texture_grid(cap, mini, 16, size_mm=50.0) == TextureGrid(16, 50.0)


@pytest.mark.slow
def test_learned_measurements_match_the_true_maps(extracted, mini):
    cap, grid, meas = extracted
    model, _ = load_pretrained("mini")
    p, _ = _true_params(cap, mini, grid)
    views = torch.stack([synthesize(mini, p, "primary"), synthesize(mini, p, "secondary")], dim=1)
    with torch.no_grad():
        exact = model.measure(views).numpy()
    rel = np.abs(meas.learned - exact) / np.abs(exact).max(axis=2, keepdims=True)
    assert np.median(rel[:, 0]) < 0.02 and np.median(rel[:, 1]) < 0.02, np.median(rel, axis=(0, 2))


def _line_errors(cap, rig, grid, meas) -> np.ndarray:
    """Each line measurement's error against the exact one of the true maps, relative to its texel's largest."""
    from reconstruction.network.data import LUMITEXEL_SCALE

    p, _ = _true_params(cap, rig, grid)
    w = np.zeros((64, rig.num_leds, 3), np.float32)
    w[:, ~rig.is_bottom] = meas.line_weights
    exact = twin.measurements(rig, **p, patterns=w, transparency=np.zeros(len(meas.valid)), camera="primary",
                              visibility=True) * LUMITEXEL_SCALE
    return np.abs(meas.lines - exact) / np.abs(exact).max(axis=(1, 2), keepdims=True)


@pytest.mark.slow
def test_line_measurements_and_transparency_match_the_true_maps(extracted, mini):
    cap, grid, meas = extracted
    _, beta = _true_params(cap, mini, grid)
    rel = _line_errors(cap, mini, grid, meas)
    assert np.median(rel) < 0.02, np.median(rel)
    # ramps has a beta ramp in one region, opaque elsewhere; texels straddling the ramp's steps mix values
    err = np.abs(meas.transparency - beta)
    assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.1, (np.median(err), np.percentile(err, 95))


@pytest.mark.slow
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


@pytest.mark.slow
def test_bad_captures_are_refused(extracted, mini, tmp_path):
    cap, grid, _ = extracted
    from reconstruction.pipeline import reconstruct

    with pytest.raises(CaptureError, match="not a capture folder"):
        reconstruct(tmp_path, tmp_path / "recon", progress=False)
    broken = tmp_path / "broken"
    shutil.copytree(cap.dir, broken, ignore=shutil.ignore_patterns("ground_truth", ".lock"))
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
    with pytest.raises(ExtractionError, match="footprint must be one of"):
        extract(cap, mini, grid, _ExactAlignment(mini), footprint="box")


def _grid_uv(R: int, step_x: float, step_y: float, turn_deg: float = 0.0) -> np.ndarray:
    """The pixels (R * R, 2) of an R x R texel grid whose columns step step_x along the image's x and rows step_y
    along its y, turned by turn_deg in the image."""
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    jj, ii = np.meshgrid(np.arange(R, dtype=float), np.arange(R, dtype=float))
    x, y = jj.ravel() * step_x, ii.ravel() * step_y
    return np.stack([c * x - s * y + 100.0, s * x + c * y + 100.0], axis=1)


def _widths(fn, uv, shape) -> tuple[int, int]:
    """A width function's (kx, ky) on a grid where every texel gets the same."""
    k = np.unique(fn(uv, shape), axis=0)
    assert len(k) == 1, k
    return int(k[0, 0]), int(k[0, 1])


def test_footprint_widths():
    """Step 2's filter widths from a view's texel pixels: "cell" the largest odd k <= d along each image axis, d the
    cell's extent there (no photosite centre more than half a pixel outside the cell; none where both are 1: the mini
    rig's ~2 px a texel), narrower where the grid is turned in the image (the box's corners must stay in); "gaussian"
    the reference's 2 ceil(d/2 + 1) - 1 of the largest step, none at 1.5 px or less; "point" none."""
    from reconstruction.stages.extraction import FOOTPRINTS

    cell, gaussian, point = (FOOTPRINTS[f][0] for f in ("cell", "gaussian", "point"))
    for d, k in ((2.2, 0), (2.9, 0), (3.0, 3), (4.9, 3), (5.0, 5), (7.4, 7), (8.0, 7)):
        assert _widths(cell, _grid_uv(4, d, d), (4, 4)) == ((k, k) if k else (0, 0)), d
    assert _widths(cell, _grid_uv(4, 5.4, 3.4), (4, 4)) == (5, 3)  # a view foreshortened along y
    assert _widths(cell, _grid_uv(4, 3.4, 1.8), (4, 4)) == (3, 1)
    # turned by 45 degrees, a 6 px cell holds a 3 px box (its corner 2.1 px out along the diagonal), not a 5 px one
    assert _widths(cell, _grid_uv(4, 6.0, 6.0, 45.0), (4, 4)) == (3, 3)
    for d, k in ((1.5, 0), (2.2, 5), (7.4, 9)):
        assert _widths(gaussian, _grid_uv(4, d, 1.0), (4, 4)) == (k, k), d
    empty = np.full((16, 2), np.nan)
    assert _widths(cell, empty, (4, 4)) == _widths(gaussian, empty, (4, 4)) == (0, 0)
    assert _widths(point, _grid_uv(4, 8, 8), (4, 4)) == (0, 0)


def test_cell_widths_follow_each_texels_cell():
    """A perspective view's cells grow across the field (a tilted camera's near side): each texel's box is its own
    cell's, so the larger cells are read whole and the smaller ones stay inside theirs; a texel whose neighbour's
    pixel is unknown (off the photo) gets none (the unknown texel reads NaN whatever its width)."""
    from reconstruction.stages.extraction import FOOTPRINTS

    R = 8
    steps = np.linspace(4.4, 6.4, R - 1)  # the step between columns j and j + 1 grows along x
    x = np.r_[0.0, np.cumsum(steps)] + 50.0
    jj, ii = np.meshgrid(np.arange(R), np.arange(R))
    uv = np.stack([x[jj.ravel()], 50.0 + 6.0 * ii.ravel()], axis=1)
    k = FOOTPRINTS["cell"][0](uv, (R, R)).reshape(R, R, 2)
    d = np.gradient(x)  # each texel's own cell extent along x (central differences, one-sided at the ends)
    want = np.where(d >= 5.0 / 1.02, 5, 3)
    assert np.array_equal(k[0, :, 0], want) and set(want) == {3, 5}
    assert (k[..., 1] == 5).all()
    uv[R + 3] = np.nan
    k = FOOTPRINTS["cell"][0](uv, (R, R)).reshape(R, R, 2)
    assert (k[0, 3] == 0).all() and (k[1, 2] == 0).all() and (k[1, 4] == 0).all() and (k[3, 3] > 0).all()


def test_cells_without_a_box_are_read_at_their_midpoints():
    """Cells under 3 px (the mini rig's ~2.1 px a texel at 48^2) hold no box; over 1.5 px they are read at the midpoints
    of an m x m split (m = ceil of the step), which is their mean over the cell: exact on a linear image (the
    midpoints are symmetric about the centre and the lookup is exact on it), and iid pixel noise averaged over the
    cell's ~5 photosites instead of the ~1-4 that the centre's lookup reads. Boxes (5.4 px) and ~1 px cells (the
    paper rig at 1024^2) keep their reading; a texel next to an unknown one is read at its centre."""
    from reconstruction.stages.extraction import FOOTPRINTS, _cell_points, _reader, _sample, _texel_jacobians

    cell = FOOTPRINTS["cell"][0]
    for d, m in ((2.2, 3), (2.9, 3), (1.7, 2), (1.2, 1)):
        uv = _grid_uv(4, d, d)
        assert np.unique(_cell_points(_texel_jacobians(uv, (4, 4)), cell(uv, (4, 4))), axis=0).tolist() == [[m, m]], d
    uv = _grid_uv(4, 5.4, 5.4)
    assert np.unique(_cell_points(_texel_jacobians(uv, (4, 4)), cell(uv, (4, 4))), axis=0).tolist() == [[1, 1]]
    uv = _grid_uv(4, 2.2, 2.2)
    uv[5] = np.nan
    m = _cell_points(_texel_jacobians(uv, (4, 4)), cell(uv, (4, 4))).reshape(4, 4, 2)
    assert (m[0, 1] == 1).all() and (m[1, 0] == 1).all() and (m[3, 3] == 3).all()

    R, d = 24, 2.2
    uv = _grid_uv(R, d, d * 0.7, 20.0) - 80.0  # foreshortened and turned, as the secondary view's cells are
    yy, xx = np.mgrid[0:80, 0:80].astype(np.float64)
    linear = (0.3 * xx - 0.2 * yy + 40.0)[..., None].astype(np.float32)
    grid = (R, R)
    reader = _reader(linear.shape, uv, cell(uv, grid), grid)
    assert {s for *_, s in reader} == {3 * 2}  # ceil(2.2) x ceil(1.54)
    want = 0.3 * uv[:, 0] - 0.2 * uv[:, 1] + 40.0
    np.testing.assert_allclose(_sample(linear, reader, "cell")[:, 0], want, rtol=0, atol=1e-4)
    rng = np.random.default_rng(1)
    noise = rng.standard_normal((80, 80, 1)).astype(np.float32)
    at_midpoints = _sample(noise, reader, "cell")[:, 0]
    at_centre = _sample(noise, _reader(noise.shape, uv, cell(uv, grid)), "cell")[:, 0]
    assert at_midpoints.std() < 0.7 * at_centre.std()


def test_the_cell_footprint_reads_its_own_cell_and_averages_the_noise():
    """Closed form: texels 8 px apart on an image that is constant over each texel's cell (another value per
    cell), centres between pixels as a grid's fall. "cell" (a 7 px box, then the bilinear lookup) returns each
    cell's own value exactly, and with iid pixel noise sigma its error has the standard deviation of the weights'
    norm, sigma (6.5 / 49) (two overlapping 7 px boxes a side) against sigma / 2 at the centre alone ("point");
    the reference's Gaussian (9 px) takes the neighbours' values in."""
    from reconstruction.stages.extraction import FOOTPRINTS, _reader, _sample, _taps

    R, d, sigma = 16, 8, 0.1
    rng = np.random.default_rng(0)
    cells = rng.uniform(1.0, 2.0, (R, R))
    img = np.kron(cells, np.ones((d, d)))[..., None].repeat(3, axis=2).astype(np.float32)
    jj, ii = np.meshgrid(np.arange(R), np.arange(R))
    uv = np.stack([jj.ravel() * d + (d - 1) / 2, ii.ravel() * d + (d - 1) / 2], axis=1)
    inner = ((ii > 0) & (ii < R - 1) & (jj > 0) & (jj < R - 1)).ravel()  # away from the image's border

    def read(footprint, image):
        reader = _reader(image.shape, uv, FOOTPRINTS[footprint][0](uv, (R, R)))
        return _sample(image, reader, footprint)[:, 0] - cells.ravel()

    assert _widths(FOOTPRINTS["cell"][0], uv, (R, R)) == (7, 7)
    assert _widths(FOOTPRINTS["gaussian"][0], uv, (R, R)) == (9, 9)
    assert np.abs(read("cell", img)).max() < 1e-6
    # read from the window the boxes reach, the same bits as the whole image filtered (on the image's border too)
    from reconstruction.stages.alignment import bilinear_at
    from reconstruction.stages.extraction import _box

    edge = np.r_[uv[:R], [[0.0, 0.0], [R * d - 1.0, 3.0], [np.nan, 5.0]]]
    whole = bilinear_at(_box(img, (7, 7)), _taps(img.shape, edge))
    np.testing.assert_array_equal(_sample(img, _reader(img.shape, edge, np.full((len(edge), 2), 7)), "cell"),
                                  whole.astype(np.float32))
    assert np.abs(read("gaussian", img)[inner]).max() > 1e-2  # sigma 1.7 px: ~2% of a neighbour one unit off
    noisy = (img + sigma * rng.standard_normal(img.shape)).astype(np.float32)
    # 196 inner texels: the sample standard deviation is within ~15% of the true one
    assert read("cell", noisy)[inner].std() == pytest.approx(sigma * 6.5 / 49, rel=0.2)
    assert read("point", noisy)[inner].std() == pytest.approx(sigma / 2, rel=0.2)


def test_footprint_choices_agree():
    """The reconstruction's config and `hemicube reconstruct --footprint` offer extraction's methods, no others."""
    import argparse

    from reconstruction.cli import register
    from reconstruction.stages.extraction import FOOTPRINTS
    from reconstruction.pipeline import ReconstructConfig

    sub = argparse.ArgumentParser().add_subparsers()
    register(sub)
    action = next(a for a in sub.choices["reconstruct"]._actions if a.dest == "footprint")
    assert set(action.choices) == set(FOOTPRINTS) and ReconstructConfig().footprint in FOOTPRINTS
    with pytest.raises(ValueError, match="footprint must be one of"):
        ReconstructConfig(footprint="box")


def test_taps_once_sample_as_bilinear_does():
    """A view's bilinear taps, computed once (extraction samples every photo of a view at the same points), then
    applied to several images: bilinear interpolation reproduces an affine image exactly (closed form, float64 to
    1e-12), on the last row and column too; NaN outside the image and at NaN points; the same bits as bilinear of
    each image; taps of another image size are refused."""
    from reconstruction.stages.alignment import bilinear, bilinear_at, bilinear_taps

    rng = np.random.default_rng(4)
    x = np.r_[rng.uniform(0, 39, 500), 39.0, 0.0, -0.5, 40.5, np.nan]
    y = np.r_[rng.uniform(0, 29, 500), 29.0, 29.0, 3.0, 3.0, 2.0]
    taps = bilinear_taps((30, 40), x, y)
    rows, cols = np.mgrid[0:30, 0:40]
    for a, b, c in ((0.5, 0.01, -0.02), (2.0, -0.03, 0.07)):
        img = np.stack([a + b * cols + c * rows, a - c * cols + b * rows], axis=2)
        got = bilinear_at(img, taps)
        inside = np.arange(len(x)) < len(x) - 3
        np.testing.assert_allclose(got[inside], np.stack([a + b * x + c * y, a - c * x + b * y], 1)[inside],
                                   rtol=0, atol=1e-12)
        assert np.isnan(got[~inside]).all()
        assert np.array_equal(got, bilinear(img, x, y), equal_nan=True)
    with pytest.raises(ValueError, match="taps for an image"):
        bilinear_at(np.zeros((31, 40, 3)), taps)


@pytest.mark.slow
def test_malvar2004_photos_are_read_from_the_captured_mosaic(extracted, mini):
    """Step 0: a captured photo is the HDR merge's bilinear demosaic of its mosaic, which keeps each photosite's own
    colour, so the mosaic read back from it and demosaiced bilinearly again gives the photo to float32 rounding; the
    Malvar-He-Cutler measurements of ramps (smooth, no edge for the two to differ at) then match the exact ones as the
    bilinear ones do (test_line_measurements_and_transparency_match_the_true_maps: median 2% of a texel's largest)."""
    from twin.camera.bayer import demosaic, mosaic

    cap, grid, meas = extracted
    bayer = mini.camera("primary").sensor.bayer
    img = cap.photo(0, 0)
    np.testing.assert_allclose(demosaic(mosaic(img, bayer), bayer), img, rtol=1e-6, atol=0)
    sharp = extract(cap, mini, grid, _ExactAlignment(mini), demosaic="malvar2004")
    rel = _line_errors(cap, mini, grid, sharp)
    assert sharp.valid.all() and np.median(rel) < 0.02, np.median(rel)
    assert not np.array_equal(sharp.lines, meas.lines)  # another demosaic, not the bilinear photos again
    with pytest.raises(ExtractionError, match="demosaic must be one of"):
        extract(cap, mini, grid, _ExactAlignment(mini), demosaic="vng")


def test_spill_texels_are_the_neighbours_of_a_much_brighter_highlight():
    """ReconstructConfig.spill_ratio's texels: every 8-neighbour of a texel whose specular peak rho_s / (alpha_x
    alpha_y) is more than `ratio` times theirs, and no other (the bright texel itself, a uniform field, a neighbour
    just under the ratio)."""
    from reconstruction.stages.fitting import FitResult
    from reconstruction.pipeline import ReconstructConfig, spill_texels

    R, C = 6, 7
    n = R * C
    alpha = np.full(n, 0.5, np.float32)
    rho_s = np.full((n, 3), 0.2, np.float32)

    def fit(a, s):
        return FitResult(np.zeros((n, 3)), np.zeros((n, 3)), a, a, np.zeros((n, 3)), s)

    assert not spill_texels(fit(alpha, rho_s), (R, C), 4.0).any()
    a = alpha.copy()
    a[2 * C + 3] = 0.2  # peak 0.2 / 0.04 = 5, against 0.2 / 0.25 = 0.8 around it: 6.25 times
    got = spill_texels(fit(a, rho_s), (R, C), 4.0)
    want = np.zeros((R, C), bool)
    want[1:4, 2:5] = True
    want[2, 3] = False
    np.testing.assert_array_equal(got, want)
    assert not spill_texels(fit(a, rho_s), (R, C), 6.5).any()
    with pytest.raises(ValueError, match="spill_ratio must be a number > 1 or None"):
        ReconstructConfig(spill_ratio=0.5)
    assert ReconstructConfig(spill_ratio=None).spill_ratio is None
