"""Novel views and lights (reconstruction.evaluation.novel_views): the fixed 560 pairs, the renderer against
independent oracles (a Lambertian plate's closed form; Mitsuba 3's GGX distribution and Smith G1 for a GGX texel),
the scores' sanity (the truth against itself is exactly 1; constant and perturbed maps fail the goals) and
`hemicube compare`."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

import hemicube.cli
import twin
from reconstruction.evaluation.metrics import check
from reconstruction.evaluation.novel_views import (LIGHTS, MAX_ZENITH_DEG, VIEWS, fibonacci_cap, novel_view_scores,
                                                   render, truth_images, validation_set)
from reconstruction.evaluation.validation import NOVEL_GOALS
from twin.materials.samples import SVBRDFMaps, load_sample, write_maps


@pytest.fixture(scope="module")
def mini_set():
    return validation_set(twin.load_rig("mini"))


def _constant(size_mm=100.0, n=24, normal=(0.0, 0.0, 1.0), tangent=(1.0, 0.0, 0.0), rho_d=(0.5, 0.4, 0.3),
              rho_s=(0.0, 0.0, 0.0), alpha=(0.3, 0.3)) -> SVBRDFMaps:
    full = lambda v: np.broadcast_to(np.asarray(v, np.float64), (n, n, len(v))).copy()  # noqa: E731
    return SVBRDFMaps(full(rho_d), full(rho_s), full(alpha), full(normal), full(tangent), np.zeros((n, n)), size_mm)


@pytest.mark.parametrize("rig_name", ["mini", "paper"])
def test_the_validation_set_is_560_pairs_spread_over_the_cap(rig_name):
    """20 views and 28 lights, zenith <= 60 deg, equal-area bands (z evenly spaced); each view a camera with the
    primary's intrinsics at the primary's distance, aimed at the sample's centre; each light the centre of an 8 x 8
    group of one board's LEDs with their summed intensity (the paper rig), or one LED (the mini rig)."""
    rig = twin.load_rig(rig_name)
    vset = validation_set(rig)
    assert vset.views.shape == (VIEWS, 3) and vset.lights.shape == (LIGHTS, 3) and VIEWS * LIGHTS == 560
    for dirs in (vset.views, vset.lights):
        assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
        z = np.sort(dirs[:, 2])
        assert z.min() >= math.cos(math.radians(MAX_ZENITH_DEG)) and np.allclose(np.diff(z), np.diff(z)[0])
    origin = np.asarray(rig.sample.origin)
    dist = np.linalg.norm(rig.primary.centre - origin)
    for d, name in zip(vset.views, vset.view_names):
        cam = vset.lights_rig.cameras[name]
        assert np.allclose(cam.centre, origin + dist * d) and np.array_equal(cam.K, rig.primary.K)
        assert (cam.width, cam.height) == (rig.primary.width, rig.primary.height)
        uv, _ = cam.project(origin[None], distort=False)
        assert np.allclose(uv[0], cam.K[:2, 2], atol=1e-6)  # aimed at the centre
    leds = rig.leds
    for k in range(LIGHTS):
        group = vset.light_leds[k]
        assert len(group) == (64 if rig_name == "paper" else 1) and len(np.unique(leds.board[group])) == 1
        if rig_name == "paper":
            assert np.ptp(leds.row[group]) == 7 and np.ptp(leds.col[group]) == 7
        src = vset.source[k]
        assert np.allclose(vset.lights_rig.leds.positions[src], leds.positions[group].mean(0))
        assert np.allclose(vset.lights_rig.leds.intensity[src], leds.intensity[group].sum(0))
    # nearest: no other candidate source lies closer in angle to the direction asked for
    cos = np.sum(vset.source_directions() * vset.lights, axis=1)
    assert np.all(cos > math.cos(math.radians(15.0)))


def test_fibonacci_cap_is_equal_area():
    """Archimedes: equal bands of z are equal areas on the sphere, so each direction owns 1/n of the cap."""
    d = fibonacci_cap(1000, 60.0)
    counts, _ = np.histogram(d[:, 2], bins=10, range=(0.5, 1.0))
    assert np.all(counts == 100)


@pytest.mark.parametrize("rig_name", ["mini", "paper"])
def test_a_lambertian_plate_matches_its_closed_form(rig_name, device):
    """A Lambertian plate under each light, from each view: L = I (rho_d / pi) cos(theta_i) cos(theta_l) / r^2, r in
    metres, I the group's summed intensity at its centre (Psi cosine), in float64 here; float32 kernel: 1e-5."""
    rig = twin.load_rig(rig_name)
    vset = validation_set(rig)
    maps = _constant()
    img = render(vset, maps, device)
    from twin.materials.samples import grid_positions

    pos = grid_positions(maps.size_mm, maps.shape, rig.sample).reshape(-1, 3)
    src = vset.lights_rig.leds
    d = src.positions[vset.source][None] - pos[:, None]
    r = np.linalg.norm(d, axis=-1)
    cos_i = d[..., 2] / r
    cos_l = -np.sum(d / r[..., None] * src.normals[vset.source][None], -1)
    want = (np.asarray(maps.rho_d[0, 0]) / np.pi * src.intensity[vset.source][None]
            * (cos_i * cos_l / (r * 1e-3) ** 2)[..., None])
    got = img.reshape(VIEWS, LIGHTS, -1, 3).transpose(0, 2, 1, 3)
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), rtol=1e-5, atol=0)


def test_a_ggx_texel_matches_mitsuba(device):
    """One anisotropic GGX texel (tilted normal, turned tangent) at one view and one light against Mitsuba 3's GGX
    distribution and Smith G1 (the reference's convention: separable G, Schlick F0 = 0.04), assembled as
    L = I Psi / r^2 cos(theta_i) (rho_d / pi + rho_s D G1 G1 F / (4 cos(theta_i) cos(theta_o))); float32: 1e-4."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    rig = twin.load_rig("mini")
    vset = validation_set(rig)
    n = np.array([0.12, -0.08, 1.0])
    n /= np.linalg.norm(n)
    t = np.cross([0.3, 1.0, 0.0], n)
    t /= np.linalg.norm(t)
    ax, ay = 0.25, 0.1
    maps = _constant(n=12, normal=n, tangent=t, rho_d=(0.2, 0.3, 0.4), rho_s=(0.8, 0.7, 0.6), alpha=(ax, ay))
    img = render(vset, maps, device)
    from twin.materials.samples import grid_positions

    p = grid_positions(maps.size_mm, maps.shape, rig.sample)[5, 7]
    frame = np.stack([t, np.cross(n, t), n])
    md = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, ax, ay, False)
    src = vset.lights_rig.leds
    checked = 0
    for v, k in ((0, 0), (7, 19), (13, 4)):
        s = vset.source[k]
        wi = src.positions[s] - p
        r = np.linalg.norm(wi)
        wi /= r
        wo = vset.lights_rig.cameras[vset.view_names[v]].centre - p
        wo /= np.linalg.norm(wo)
        li, lo = frame @ wi, frame @ wo
        h = (li + lo) / np.linalg.norm(li + lo)
        vec = lambda x: mi.Vector3f(*map(float, x))  # noqa: E731
        D = md.eval(vec(h))
        G = md.smith_g1(vec(li), vec(h)) * md.smith_g1(vec(lo), vec(h))
        F = 0.04 + 0.96 * (1.0 - float(np.dot(li, h))) ** 5
        f = np.array([0.2, 0.3, 0.4]) / np.pi + np.array([0.8, 0.7, 0.6]) * D * G * F / (4 * li[2] * lo[2])
        want = src.intensity[s] * max(0.0, -float(np.dot(wi, src.normals[s]))) / (r * 1e-3) ** 2 * li[2] * f
        np.testing.assert_allclose(img[v, k, 5, 7], want, rtol=1e-4)
        checked += 1
    assert checked == 3


def test_the_truth_against_itself_scores_exactly_one(mini_set):
    truth = load_sample("satin", resolution=32)
    s = novel_view_scores(mini_set, truth, truth)
    assert s["ssim"] == {"mean": 1.0, "p5": 1.0, "worst": 1.0}
    assert s["rel_rmse"]["worst"] == 0.0 and s["psnr_db"]["worst"] == math.inf
    assert len(s["pairs"]) == 560 and all(check({"novel": s}, NOVEL_GOALS)[i]["passed"] for i in range(2))


def _tilted(maps: SVBRDFMaps, deg: float) -> SVBRDFMaps:
    a = math.radians(deg)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])
    n = np.asarray(maps.normal, np.float64) @ rot.T
    t = np.asarray(maps.tangent, np.float64)
    t = t - np.sum(t * n, -1, keepdims=True) * n
    return replace(maps, normal=n, tangent=t / np.linalg.norm(t, axis=-1, keepdims=True))


@pytest.mark.parametrize("name", ["ramps", "satin", "metal"])
def test_constant_and_perturbed_maps_fail_the_goals(mini_set, name):
    """Each map replaced by its mean, alpha x 1.5, and every normal tilted 5 deg: each misses a goal (the default
    sample and two glossy suite samples; on a diffuse-dominated sample a uniform tilt only shifts brightness
    smoothly, which SSIM discounts: docs/accuracy.md)."""
    truth = load_sample(name, resolution=48)
    mean = lambda a: np.broadcast_to(np.asarray(a).mean(axis=(0, 1)), a.shape).copy()  # noqa: E731
    wrong = {"constant": replace(truth, rho_d=mean(truth.rho_d), rho_s=mean(truth.rho_s),
                                 alpha=np.exp(mean(np.log(truth.alpha)))),
             "alpha x 1.5": replace(truth, alpha=np.clip(truth.alpha * 1.5, None, 1.0)),
             "tilted 5 deg": _tilted(truth, 5.0)}
    for what, maps in wrong.items():
        rows = check({"novel": novel_view_scores(mini_set, truth, maps)}, NOVEL_GOALS)
        assert not all(r["passed"] for r in rows), (what, rows)


def test_the_truths_radiance_is_box_filtered_onto_the_grid(mini_set):
    """A truth finer than the grid: its radiance averaged over each grid texel. A Lambertian checkerboard of the
    truth's texels (0.2 / 0.8) reads as its mean albedo (0.5) on a grid of 2 x 2 truth texels a texel, to the
    irradiance's change within a texel (1 %); maps already on the grid are rendered as they are."""
    n, r = 16, 8
    board = np.where((np.arange(n)[:, None] + np.arange(n)[None, :]) % 2 == 0, 0.2, 0.8)
    fine = replace(_constant(n=n), rho_d=np.repeat(board[..., None], 3, axis=2))
    mean = _constant(n=r, rho_d=(0.5, 0.5, 0.5))
    got = truth_images(mini_set, fine, fine.size_mm, r)
    want = render(mini_set, mean)
    np.testing.assert_allclose(got[:, :, 1:-1, 1:-1], want[:, :, 1:-1, 1:-1], rtol=1e-2)
    assert np.array_equal(truth_images(mini_set, mean, mean.size_mm, r), want)


def test_compare_two_map_folders(tmp_path, capsys):
    """`hemicube compare TRUTH RECON`: exit 0 on the truth against itself, exit 1 (naming the worst pair) on
    constant maps; --json holds every pair."""
    truth = load_sample("ramps", resolution=64)
    a = write_maps(truth, tmp_path / "truth")
    grid = load_sample("ramps", resolution=32)
    flat = replace(grid, rho_d=np.broadcast_to(np.asarray(grid.rho_d).mean((0, 1)), grid.rho_d.shape).copy())
    b = write_maps(flat, tmp_path / "flat")
    assert hemicube.cli.main(["compare", str(a), str(a), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["passed"] and len(doc["novel"]["pairs"]) == 560 and doc["novel"]["ssim"]["worst"] == 1.0
    assert hemicube.cli.main(["compare", str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out and "worst" in out and "light" in out
    assert hemicube.cli.main(["compare", str(a), str(tmp_path / "nothing")]) == 2
