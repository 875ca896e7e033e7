"""The material suite (twin.material_suite, issue #14): one procedural sample per OpenSVBRDF category plus
`quadrants`. Checked here: registration, valid maps, determinism and seed dependence, the ranges the suite
must cover together, each category's character on its default AND its held-back compositions, and the
OpenSVBRDF folder round trip.

HELD_BACK names the held-back variants (other seeds = other compositions of each category) that the
pipeline's tuning never looked at (issue #14 item 3): `test_held_back_end_to_end` runs them through the
validation (capture, reconstruct, score against the suite goals) when HEMICUBE_SUITE_E2E=1 is set (about
100 s a sample on one core, so not in the default run).
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from twin.material_suite import BUILDERS, SUITE_SAMPLES, parameter_ranges, suite_table
from twin.samples import BUILTIN_SAMPLES, SVBRDFMaps, builtin_sample, load_sample, read_maps, write_maps

RES = 128  # what `hemicube validate --sample NAME` captures
SEEDS = (0, 1, 2, 3)  # compositions whose character is checked (the default is seed 0)
HELD_BACK = tuple(f"{name}@{9001 + k}" for k, name in enumerate(SUITE_SAMPLES))


@pytest.fixture(scope="module")
def suite() -> dict:
    return {(name, seed): builtin_sample(name, RES, seed) for name in SUITE_SAMPLES for seed in SEEDS}


def test_registered_as_builtins():
    assert set(SUITE_SAMPLES) == set(BUILDERS) and len(SUITE_SAMPLES) == 10
    assert set(SUITE_SAMPLES) <= set(BUILTIN_SAMPLES)
    assert BUILTIN_SAMPLES[:3] == ("ramps", "brushed_metal", "satin_weave")  # the old ones stay first
    assert load_sample("wood", resolution=32).name == "wood"


@pytest.mark.parametrize("name", SUITE_SAMPLES)
def test_deterministic_and_seeded(name):
    a, b, c = builtin_sample(name, 48, 5), builtin_sample(name, 48, 5), builtin_sample(name, 48, 6)
    for k in SVBRDFMaps.ARRAYS:
        assert getattr(a, k).tobytes() == getattr(b, k).tobytes(), k
    assert any(getattr(a, k).tobytes() != getattr(c, k).tobytes() for k in SVBRDFMaps.ARRAYS)
    assert builtin_sample(name, 16).shape == (16, 16) and builtin_sample(name, 17).shape == (17, 17)


def test_name_at_seed_loads_a_held_back_composition():
    m = load_sample("metal@7", resolution=32)
    want = builtin_sample("metal", 32, 7)
    assert m.name == "metal" and m.rho_s.tobytes() == want.rho_s.tobytes()
    assert load_sample("metal@7", resolution=32).alpha.tobytes() != load_sample("metal", 32).alpha.tobytes()


def test_valid_maps_in_the_export_convention(suite):
    for (name, seed), m in suite.items():
        assert isinstance(m, SVBRDFMaps)  # construction validates ranges, unit and orthogonal frames, n_z > 0
        assert np.all(m.alpha[..., 0] >= m.alpha[..., 1]), (name, seed)  # αx ≥ αy as built (reference §5)
        assert np.all(m.transparency == 0), name


def test_the_suite_covers_the_issues_ranges(suite):
    """Issue #14: together α 0.01-0.6, αx/αy up to 8, ρd 0.01-0.9, ρs up to the reference's range (paper's
    ps_range is 20; the suite reaches > 15), normal tilts up to 25°, at the default seed."""
    r = [parameter_ranges(suite[(name, 0)]) for name in SUITE_SAMPLES]
    lo = lambda k: min(x[k][0] for x in r)  # noqa: E731
    hi = lambda k: max(x[k][1] for x in r)  # noqa: E731
    assert lo("alpha_y") <= 0.0101 and hi("alpha_x") >= 0.599
    assert hi("anisotropy") >= 7.99
    assert lo("rho_d") <= 0.0101 and hi("rho_d") >= 0.89
    assert hi("rho_s") >= 15.0
    assert hi("tilt_deg") >= 25.0


def _median_ratio(m):
    return float(np.median(m.alpha[..., 0] / m.alpha[..., 1]))


def test_each_category_keeps_its_character_on_every_seed(suite):
    """The paper's Fig. 12 traits, on the default and the other checked compositions."""
    for seed in SEEDS:
        s = {name: suite[(name, seed)] for name in SUITE_SAMPLES}
        for name in ("satin", "wood", "woven"):  # strong anisotropy
            assert _median_ratio(s[name]) >= 4.0, (name, seed)
        assert s["metal"].rho_d.max() <= 0.0401 and s["metal"].rho_s.max(axis=2).min() >= 4.0  # ρd ~ 0, bright ρs
        assert _median_ratio(s["metal"]) < 1.01 and (s["metal"].alpha[..., 0] / s["metal"].alpha[..., 1]).max() > 6
        c = s["ceramic"]  # a narrow, weak highlight
        assert c.alpha.max() <= 0.046 and c.alpha.min() <= 0.013 and c.rho_s.max() <= 0.75
        for name in ("paper", "fabric"):  # rough, weakly specular (where it is not ink or foil)
            m = s[name]
            assert np.median(m.alpha[..., 0]) >= 0.4 and np.median(m.rho_s) <= 0.35, (name, seed)
        assert s["paper"].rho_s.max() >= 11.0  # the foil stamp: paper's ps_range is 20 (reference §5)
        tilt = lambda m: np.degrees(np.arccos(m.normal[..., 2].astype(np.float64)))  # noqa: E731
        assert tilt(s["leather"]).max() >= 24.0 and np.median(tilt(s["leather"])) >= 3.0
        assert 5.0 <= tilt(s["wallpaper"]).max() <= 9.0  # embossed ornament (6°) on a vinyl grain (2°)
        q = parameter_ranges(s["quadrants"])
        assert q["anisotropy"][0] <= 1.0001 and q["anisotropy"][1] >= 7.99 and q["tilt_deg"][1] >= 19.0


def test_draws_the_same_sample_at_every_resolution():
    """Sizes are fractions of the side: the 64² and 128² maps of a seed agree where their texels coincide
    in character (ranges within a few per cent)."""
    for name in SUITE_SAMPLES:
        a, b = parameter_ranges(builtin_sample(name, 64)), parameter_ranges(builtin_sample(name, 128))
        for k in ("rho_d", "rho_s", "alpha_x", "alpha_y"):
            np.testing.assert_allclose(a[k], b[k], rtol=0.12, atol=0.01, err_msg=f"{name} {k}")


def test_written_and_read_as_opensvbrdf_maps(tmp_path):
    for name in SUITE_SAMPLES:
        m = builtin_sample(name, 32, 3)
        r = read_maps(write_maps(m, tmp_path / name))
        assert (r.name, r.size_mm) == (name, 120.0)
        for k in ("rho_d", "rho_s", "alpha", "transparency"):
            assert getattr(r, k).tobytes() == getattr(m, k).tobytes(), (name, k)
        np.testing.assert_allclose(r.normal, m.normal, atol=2e-7)
        np.testing.assert_allclose(r.tangent, m.tangent, atol=2e-7)


def test_suite_table_lists_every_sample_with_its_ranges():
    rows = suite_table(resolution=32)
    assert [r["name"] for r in rows] == list(SUITE_SAMPLES)
    for r in rows:
        assert r["summary"] and r["category"]
        assert set(r["ranges"]) == {"rho_d", "rho_s", "alpha_x", "alpha_y", "anisotropy", "tilt_deg", "transparency"}
        assert all(lo <= hi for lo, hi in r["ranges"].values())


@pytest.mark.skipif(os.environ.get("HEMICUBE_SUITE_E2E") != "1",
                    reason="end to end on the held-back samples: ~100 s each; set HEMICUBE_SUITE_E2E=1")
@pytest.mark.parametrize("sample", HELD_BACK)
def test_held_back_end_to_end(sample, tmp_path):
    """The issue's goals on a held-back composition (mini rig, 48² grid, default configuration)."""
    import twin
    from reconstruction.metrics import Threshold, check
    from reconstruction.pipeline import ReconstructConfig, reconstruct
    from reconstruction.validation import evaluate
    from twin.capture import capture

    rig = twin.load_rig("mini")
    cap = capture(rig, sample, tmp_path / "capture", seed=1, progress=False)
    recon = reconstruct(cap, tmp_path / "reconstruction", ReconstructConfig(), progress=False, rig=rig)
    metrics, _ = evaluate(cap, recon, rig)
    goals = [Threshold("alignment.median_px", "<=", 0.5, "issue #14"),
             Threshold("maps.normal_deg.median", "<=", 1.0, "issue #14"),
             Threshold("maps.alpha_x_pct.median", "<=", 10.0, "issue #14"),
             Threshold("maps.alpha_y_pct.median", "<=", 10.0, "issue #14"),
             Threshold("maps.rho_d_pct.median", "<=", 3.0, "issue #14"),
             Threshold("maps.rho_s_pct.median", "<=", 10.0, "issue #14"),
             Threshold("render.maps.ssim", ">=", 0.93, "issue #14")]
    if metrics["maps"]["tangent_deg"]["count"]:
        goals.append(Threshold("maps.tangent_deg.median", "<=", 5.0, "issue #14"))
    rows = check(metrics, goals)
    assert all(r["passed"] for r in rows), [r for r in rows if not r["passed"]]
