"""The validation report: golden map errors, image scores against closed forms, thresholds, the report folder."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from reconstruction.evaluation.metrics import (
    Threshold, check, flatten_metrics, format_table, image_scores, map_errors, resample_maps, truth_coverage,
)
from reconstruction.evaluation.report import Panel, RenderPanel, map_panels, render_panel, write_report
from twin.materials.samples import canonical_anisotropy, load_sample

RES = 32
STATS = ("median", "mean", "p90")


@pytest.fixture(scope="module")
def ramps():
    return load_sample("ramps", resolution=RES)


def rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def n_anisotropic(maps, ratio=1.5) -> int:
    a = maps.alpha.astype(np.float64)
    return int((np.maximum(a[..., 0], a[..., 1]) >= ratio * np.minimum(a[..., 0], a[..., 1])).sum())


# --- map errors -------------------------------------------------------------------------------------


def test_identical_maps_have_zero_errors(ramps):
    m = map_errors(ramps, ramps)
    assert m["texels"] == RES * RES
    for k in ("normal_deg", "tangent_deg", "log_alpha_x", "log_alpha_y", "alpha_x_pct", "alpha_y_pct",
              "rho_d_pct", "rho_s_pct", "transparency_abs"):
        for s in STATS:
            assert m[k][s] == 0.0, (k, s)
    assert m["tangent_deg"]["count"] == n_anisotropic(ramps) > 0
    assert m["rho_d_pct"]["count"] == 3 * RES * RES and m["rho_d_pct"]["g"]["count"] == RES * RES


def test_normals_rotated_5_degrees(ramps):
    r = rot_x(5.0)  # ramps' normals tilt about x (0..40°) so all stay in the upper hemisphere
    rec = dataclasses.replace(ramps, normal=ramps.normal @ r.T, tangent=ramps.tangent @ r.T)
    m = map_errors(ramps, rec)
    for s in STATS:
        assert m["normal_deg"][s] == pytest.approx(5.0, abs=1e-3)


def test_tangent_sign_is_irrelevant_and_90_degrees_is_90(ramps):
    flipped = dataclasses.replace(ramps, tangent=-ramps.tangent)
    assert map_errors(ramps, flipped)["tangent_deg"]["p90"] < 1e-4
    turned = dataclasses.replace(ramps, tangent=ramps.bitangent)  # rotated 90° about n
    m = map_errors(ramps, turned)
    for s in STATS:
        assert m["tangent_deg"][s] == pytest.approx(90.0, abs=1e-3)
    assert m["normal_deg"]["p90"] == 0.0


def test_swapped_alpha_with_swapped_axis_is_the_same_brdf(ramps):
    # αx <-> αy with t -> n × t is the same BRDF; the canonical ordering on both sides must see no error
    swapped = dataclasses.replace(ramps, alpha=ramps.alpha[..., ::-1], tangent=ramps.bitangent)
    assert not np.array_equal(canonical_anisotropy(swapped).alpha, swapped.alpha)
    m = map_errors(ramps, swapped)
    for k in ("tangent_deg", "log_alpha_x", "log_alpha_y"):
        assert m[k]["p90"] < 1e-4, k


def test_alpha_scaled_by_1_1(ramps):
    m = map_errors(ramps, dataclasses.replace(ramps, alpha=ramps.alpha * 1.1))
    for ax in "xy":
        for s in STATS:
            assert m[f"log_alpha_{ax}"][s] == pytest.approx(math.log(1.1), abs=1e-6)
            assert m[f"alpha_{ax}_pct"][s] == pytest.approx(10.0, abs=1e-4)


def test_rho_scaled_by_1_2_is_20_percent(ramps):
    truth = dataclasses.replace(ramps, rho_d=np.clip(ramps.rho_d, 0.1, 0.8), rho_s=np.clip(ramps.rho_s, 1.0, 8.0))
    rec = dataclasses.replace(truth, rho_d=truth.rho_d * 1.2, rho_s=truth.rho_s * 1.2)
    m = map_errors(truth, rec)
    for key in ("rho_d_pct", "rho_s_pct"):
        for s in STATS:
            assert m[key][s] == pytest.approx(20.0, abs=1e-4)
            for ch in "rgb":
                assert m[key][ch][s] == pytest.approx(20.0, abs=1e-4)


def test_rho_floor_bounds_the_relative_error_of_black(ramps):
    truth = dataclasses.replace(ramps, rho_d=np.zeros_like(ramps.rho_d))
    rec = dataclasses.replace(ramps, rho_d=np.full_like(ramps.rho_d, 0.01))
    assert map_errors(truth, rec, rho_floor=(0.05, 0.5))["rho_d_pct"]["median"] == pytest.approx(20.0, abs=1e-4)
    assert map_errors(truth, rec, rho_floor=0.1)["rho_d_pct"]["median"] == pytest.approx(10.0, abs=1e-4)


def test_mask_selects_texels_and_empty_selection_is_nan(ramps):
    rho_d = ramps.rho_d.copy()
    rho_d[RES // 2:] = np.clip(rho_d[RES // 2:] + 0.2, 0.0, 1.0)  # errors only in the upper half
    rec = dataclasses.replace(ramps, rho_d=rho_d)
    lower = np.zeros((RES, RES), bool)
    lower[:RES // 2] = True
    m = map_errors(ramps, rec, mask=lower)
    assert m["texels"] == RES * RES // 2 and m["rho_d_pct"]["p90"] == 0.0
    assert map_errors(ramps, rec, mask=~lower)["rho_d_pct"]["median"] > 0
    iso = dataclasses.replace(ramps, alpha=np.full_like(ramps.alpha, 0.2))
    t = map_errors(iso, iso)["tangent_deg"]
    assert t["count"] == 0 and math.isnan(t["median"])


def test_map_errors_rejects_bad_input(ramps):
    with pytest.raises(ValueError, match="resample"):
        map_errors(ramps, load_sample("ramps", resolution=16))
    with pytest.raises(ValueError, match="boolean"):
        map_errors(ramps, ramps, mask=np.ones((RES, RES)))
    with pytest.raises(ValueError, match="shape"):
        map_errors(ramps, ramps, mask=np.ones((RES, 3), bool))
    with pytest.raises(ValueError, match="rho_floor"):
        map_errors(ramps, ramps, rho_floor=float("nan"))


# --- resampling -------------------------------------------------------------------------------------


def test_resample_identity_and_2x2_average(ramps):
    same = resample_maps(ramps, ramps.size_mm, RES)
    for k in ramps.ARRAYS:
        np.testing.assert_allclose(getattr(same, k), getattr(ramps, k), atol=1e-6, err_msg=k)
    half = resample_maps(ramps, ramps.size_mm, RES // 2)
    blocks = lambda a: a.astype(np.float64).reshape(RES // 2, 2, RES // 2, 2, *a.shape[2:])  # noqa: E731
    # a half-resolution texel centre is the corner of a 2 x 2 block: bilinear = the block mean,
    # log-space for α = the block's geometric mean
    np.testing.assert_allclose(half.rho_d, blocks(ramps.rho_d).mean(axis=(1, 3)), atol=1e-6)
    np.testing.assert_allclose(half.alpha, np.exp(np.log(blocks(ramps.alpha)).mean(axis=(1, 3))), rtol=1e-5)
    assert np.abs(np.einsum("ijk,ijk->ij", half.normal, half.tangent)).max() < 1e-6
    assert truth_coverage(ramps, ramps.size_mm, RES // 2).all()


def test_coverage_of_a_larger_grid(ramps):
    cov = truth_coverage(ramps, 150.0, 30)  # 5 mm texels, truth spans |x| <= 60 mm: columns 3..26
    expect = np.zeros(30, bool)
    expect[3:27] = True
    np.testing.assert_array_equal(cov, expect[:, None] & expect[None, :])
    big = resample_maps(ramps, 150.0, 30)
    assert big.size_mm == 150.0 and big.shape == (30, 30)


# --- image scores -----------------------------------------------------------------------------------


def _image(h=24, w=20, seed=0):
    return np.random.default_rng(seed).uniform(0.0, 2.0, (h, w, 3))


def test_ssim_of_identical_images_is_one():
    img = _image()
    s = image_scores(img, img)
    assert s["ssim"] == pytest.approx(1.0, abs=1e-12) and s["ssim_all"] == pytest.approx(1.0, abs=1e-12)
    assert s["psnr_db"] == math.inf and s["pixels"] == img.shape[0] * img.shape[1]


def test_psnr_matches_closed_form():
    from skimage.metrics import peak_signal_noise_ratio

    img = _image()
    delta = 0.01
    sign = np.where((np.indices(img.shape).sum(axis=0) % 2) == 0, 1.0, -1.0)
    noisy = img + delta * sign  # MSE = delta² exactly
    s = image_scores(img, noisy)
    rng = img.max() - img.min()
    assert s["data_range"] == pytest.approx(rng)
    assert s["psnr_db"] == pytest.approx(20.0 * math.log10(rng / delta), abs=1e-9)
    assert s["psnr_db"] == pytest.approx(peak_signal_noise_ratio(img, noisy, data_range=rng), abs=1e-9)
    assert s["ssim"] < 1.0
    assert image_scores(img, noisy, data_range=4.0)["psnr_db"] == pytest.approx(20 * math.log10(4.0 / delta))


def test_masked_pixels_do_not_count():
    img = _image()
    bad = img.copy()
    bad[:, :8] += 5.0
    mask = np.ones(img.shape[:2], bool)
    mask[:, :8] = False
    s = image_scores(img, bad, mask=mask)
    assert s["psnr_db"] == math.inf and s["ssim"] == pytest.approx(1.0) and s["pixels"] == mask.sum()
    with pytest.raises(ValueError, match="non-finite"):
        image_scores(img, np.full_like(img, np.nan))
    with pytest.raises(ValueError, match="constant"):
        image_scores(np.zeros_like(img), img)


# --- thresholds -------------------------------------------------------------------------------------


def test_thresholds_pass_fail_and_non_finite_fails():
    metrics = {"a": {"median": 0.5}, "b": 0.98, "c": math.nan, "d": math.inf, "e": None}
    ths = [Threshold("a.median", "<=", 1.0, "goal"), Threshold("a.median", ">=", 1.0, "goal"),
           Threshold("b", ">=", 0.98, "goal"), Threshold("c", "<=", 1.0, "goal"),
           Threshold("d", ">=", 1.0, "goal"), Threshold("e", "<=", 1.0, "null in JSON"),
           Threshold("missing.key", "<=", 1.0, "goal")]
    rows = check(metrics, ths)
    assert [r["passed"] for r in rows] == [True, False, True, False, False, False, False]
    assert rows[-1]["value"] is None and math.isnan(rows[3]["value"])
    table = format_table(rows)
    assert len(table.splitlines()) == 2 + len(ths)
    assert "nan" in table and "inf" in table and "missing" in table
    assert table.count("PASS") == 2 and table.count("FAIL") == 5
    lines = table.splitlines()
    col = lines[0].index("threshold")  # fixed width: every threshold starts in that column
    assert all(line[col:col + 2] in ("<=", ">=") for line in lines[2:])
    assert len({line.index(" <=" if " <=" in line else " >=") for line in lines[2:]}) == 1
    with pytest.raises(ValueError, match="op"):
        Threshold("a", "<", 1.0, "x")
    with pytest.raises(ValueError, match="finite"):
        Threshold("a", "<=", math.nan, "x")
    with pytest.raises(ValueError, match="not a number"):
        check(metrics, [Threshold("a", "<=", 1.0, "x")])


# --- the report folder ------------------------------------------------------------------------------


def test_write_report(tmp_path, ramps):
    rec = dataclasses.replace(ramps, normal=ramps.normal @ rot_x(5.0).T, tangent=ramps.tangent @ rot_x(5.0).T)
    maps = map_errors(ramps, rec)
    photo = _image(24, 28)
    metrics = {"maps": maps, "render": {"latent": image_scores(photo, photo * 1.05), "nan": math.nan,
                                        "perfect": image_scores(photo, photo)}}
    rows = check(metrics, [Threshold("maps.normal_deg.median", "<=", 1.0, "goal"),
                           Threshold("render.latent.ssim", ">=", 0.9, "ours"),
                           Threshold("render.nan", "<=", 1.0, "NaN must fail")])
    assert [r["passed"] for r in rows] == [False, True, False]
    panels = map_panels(ramps, rec) + [RenderPanel("pattern_07", photo, photo * 1.05, photo * 0.9)]
    tangent = next(p for p in panels if p.name == "tangent")  # shows the metric's own in-plane error
    assert np.nanmedian(tangent.error) == pytest.approx(maps["tangent_deg"]["median"], abs=1e-9)
    assert np.isnan(tangent.error).sum() == RES * RES - maps["tangent_deg"]["count"]
    out = tmp_path / "report"
    paths = write_report(out, title="ramps on the mini rig", metrics=metrics, checks=rows, panels=panels,
                         notes=["a note"])

    doc = json.loads(paths["metrics_json"].read_text(),
                     parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert doc["passed"] is False and len(doc["checks"]) == 3
    assert doc["metrics"]["render"]["nan"] is None  # NaN -> null
    assert doc["metrics"]["render"]["perfect"]["psnr_db"] == "inf"
    assert doc["metrics"]["maps"]["normal_deg"]["median"] == pytest.approx(5.0, abs=1e-3)
    assert check(doc["metrics"], [Threshold("render.nan", "<=", 1.0, "x")])[0]["passed"] is False

    md = paths["report_md"].read_text()
    assert "**Result: FAIL** (1 of 3 thresholds met)" in md and "a note" in md
    assert "maps.normal_deg.median = 5" in md
    names = [p.name for p in panels]
    assert sorted(paths["images"]) == sorted(names)
    import matplotlib.image as mpimg

    for name in names:
        assert f"![{name}](images/{name}.png)" in md
        png = out / "images" / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        img = (mpimg.imread(png)[..., :3] * 255).astype(np.uint32)
        colours = np.unique((img[..., 0] << 16) | (img[..., 1] << 8) | img[..., 2])
        assert img.shape[1] > img.shape[0] and colours.size > 50  # a drawn picture, wider than tall
    leftovers = [p for p in out.rglob("*") if p.name.startswith(".")]
    assert leftovers == []
    assert sorted(p.name for p in out.iterdir()) == ["images", "metrics.json", "report.md"]
    assert "normal_deg.median" in flatten_metrics(maps)


def test_render_panel_and_panel_validation(tmp_path):
    photo = _image(24, 28)
    path = render_panel("p0", photo, photo, photo * 0.5, tmp_path / "p0.png", exposure=0.5)
    assert path.read_bytes()[:4] == b"\x89PNG"
    assert [p.name for p in tmp_path.iterdir()] == ["p0.png"]
    with pytest.raises(ValueError, match="kind"):
        Panel("x", photo, photo, "bogus")
    with pytest.raises(ValueError, match="same shape"):
        Panel("x", photo, photo[:5], "rgb")
    with pytest.raises(ValueError, match="name"):
        Panel("../x", photo, photo, "rgb")
    with pytest.raises(ValueError, match="unique"):
        write_report(tmp_path / "r", title="t", metrics={}, checks=[],
                     panels=[Panel("a", photo, photo, "rgb"), Panel("a", photo, photo, "rgb")])
