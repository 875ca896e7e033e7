"""The material suite (twin.materials.suite, docs/accuracy.md): one procedural sample per OpenSVBRDF category plus
`quadrants`. Checked here: registration, valid maps, determinism and seed dependence, the ranges the suite
must cover together, each category's character on its default AND its held-back compositions, and
`hemicube samples list` (the OpenSVBRDF folder round trip of every built-in sample is in test_samples.py).

The suite and held-back compositions of it run end to end in tests/test_validate_suite.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from twin.materials.samples import (BUILTIN_SAMPLES, SUITE, SVBRDFMaps, builtin_sample, load_sample, parameter_ranges,
                                    sample_ranges)
from twin.materials.suite import BUILDERS, SUITE_SAMPLES

RES = 128  # what `hemicube validate --sample NAME` captures
SEEDS = (0, 1, 2, 3)  # compositions whose character is checked (the default is seed 0)


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


def test_the_suite_covers_the_required_ranges(suite):
    """Together α 0.01-0.6, αx/αy up to 8, ρd 0.01-0.9, ρs up to the reference's range (paper's
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


def test_samples_list_shows_every_sample_with_its_ranges():
    """`hemicube samples list` (sample_ranges): every suite sample with a character line and its spans."""
    assert SUITE == SUITE_SAMPLES
    for name in SUITE_SAMPLES:
        r = sample_ranges(name, resolution=32)
        assert r["description"] and r["description"] != name
        assert set(r) == {"rho_d", "rho_s", "alpha_x", "alpha_y", "anisotropy", "tilt_deg", "transparency",
                          "description"}
        assert all(v[0] <= v[1] for k, v in r.items() if k != "description")
