"""twin.materials.samples: the validated map model, orientation, the map-folder contract, canonical anisotropy
(checked through twin.optics.ggx.brdf) and the built-in procedural samples."""
from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

import twin.materials.samples as samples
from twin.materials.exr import read_exr_attributes, read_rgb_exr, write_rgb_exr
from twin.rig.model import SamplePlane
from twin.materials.samples import (BUILTIN_SAMPLES, MAP_FILES, RAMPS_REFERENCE, SampleError, SVBRDFMaps, builtin_sample,
                          canonical_anisotropy, load_sample, ramp_regions, read_maps, texel_positions,
                          world_to_texel, write_maps)

RES = 64  # resolution of the built-ins in most tests (fast, still > 4 texels per ramp region border)


def _fields(n=8, **over):
    """Valid plain fields for an n x n sample; keyword overrides replace whole fields."""
    f = dict(rho_d=np.full((n, n, 3), 0.4), rho_s=np.full((n, n, 3), 2.0),
             alpha=np.broadcast_to([0.2, 0.1], (n, n, 2)).copy(),
             normal=np.broadcast_to([0.0, 0.0, 1.0], (n, n, 3)).copy(),
             tangent=np.broadcast_to([1.0, 0.0, 0.0], (n, n, 3)).copy(),
             transparency=np.zeros((n, n)), size_mm=100.0, name="plain")
    f.update(over)
    return f


def _random_maps(n=12, seed=0, size_mm=90.0):
    """Valid maps with every parameter varying per texel (tilted normals, arbitrary tangents)."""
    rng = np.random.default_rng(seed)
    th, ph = np.radians(rng.uniform(0, 50, (n, n))), rng.uniform(0, 2 * np.pi, (n, n))
    normal = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    t = rng.standard_normal((n, n, 3))
    t -= np.sum(t * normal, -1, keepdims=True) * normal
    tangent = t / np.linalg.norm(t, axis=-1, keepdims=True)
    return SVBRDFMaps(rng.uniform(0, 1, (n, n, 3)), rng.uniform(0, 10, (n, n, 3)),
                      rng.uniform(0.006, 0.8, (n, n, 2)), normal, tangent, rng.uniform(0, 1, (n, n)),
                      size_mm, "random")


def _tilt_deg(normal):
    n = np.asarray(normal, dtype=np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(n[..., :2], axis=-1), n[..., 2]))


# --- the model ---------------------------------------------------------------------------------------


def test_maps_are_float32_read_only_copies():
    f = _fields()
    m = SVBRDFMaps(**f)
    for k in SVBRDFMaps.ARRAYS:
        a = getattr(m, k)
        assert a.dtype == np.float32, k
        assert not a.flags.writeable, k
        with pytest.raises(ValueError):
            a[0, 0] = 0
    f["rho_d"][0, 0] = 0.9  # the caller's array is not shared
    assert m.rho_d[0, 0, 0] == np.float32(0.4)
    assert m.shape == (8, 8) and m.resolution == 8 and m.texel_mm == 12.5
    np.testing.assert_array_equal(m.alpha_x, np.float32(0.2))
    np.testing.assert_array_equal(m.bitangent[3, 4], [0, 1, 0])  # b = n × t
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.size_mm = 3.0
    assert dataclasses.replace(m, size_mm=50.0).size_mm == 50.0


def _with(field, value_fn):
    f = _fields()
    if field in SVBRDFMaps.ARRAYS:
        a = np.array(f[field], dtype=np.float64)
        value_fn(a)
        f[field] = a
    else:
        f[field] = value_fn(None)
    return f


def _set(idx, value):
    def fn(a):
        a[idx] = value
    return fn


@pytest.mark.parametrize("field, fn, msg", [
    ("rho_s", lambda a: None, None),  # control: valid
    ("rho_d", _set((2, 5, 1), np.nan), r"rho_d: non-finite value \(0\.4, nan, 0\.4\) at texel \(row 2, col 5\)"),
    ("alpha", _set((1, 1, 0), np.inf), r"alpha: non-finite value \(inf, 0\.1\) at texel \(row 1, col 1\)"),
    ("transparency", _set((7, 0), -np.inf), r"transparency: non-finite value -inf at texel \(row 7, col 0\)"),
    ("rho_d", _set((3, 4, 0), 1.01), r"rho_d: value \(1\.01, 0\.4, 0\.4\) at texel \(row 3, col 4\) is outside \[0, 1\]"),
    ("rho_d", _set((0, 1, 2), -0.001), r"rho_d: .* at texel \(row 0, col 1\) is outside \[0, 1\]"),
    ("rho_s", _set((6, 6, 2), 20.5), r"rho_s: value \(2, 2, 20\.5\) at texel \(row 6, col 6\) is outside \[0, 20\]"),
    ("alpha", _set((2, 2, 1), 0.0), r"alpha: value \(0\.2, 0\) at texel \(row 2, col 2\) is outside \[0\.001, 1\.5\]"),
    ("alpha", _set((2, 3, 0), 1.6), r"alpha: value \(1\.6, 0\.1\) .* outside \[0\.001, 1\.5\]"),
    ("transparency", _set((4, 4), 1.5), r"transparency: value 1\.5 at texel \(row 4, col 4\) is outside \[0, 1\]"),
    ("normal", _set((5, 2), [0.0, 0.0, 1.01]), r"normal: not a unit vector at texel \(row 5, col 2\).*length 1\.01"),
    ("tangent", _set((1, 7), [0.5, 0.0, 0.0]), r"tangent: not a unit vector at texel \(row 1, col 7\)"),
    ("normal", _set((3, 3), [1.0, 0.0, 0.0]), r"normal: \(1, 0, 0\) at texel \(row 3, col 3\) is not in the upper hemisphere"),
    ("normal", _set((3, 3), [0.0, 0.0, -1.0]), r"normal: .* is not in the upper hemisphere \(n_z must be > 0\)"),
    ("tangent", _set((0, 6), [np.sqrt(0.99), 0.0, 0.1]), r"tangent: not perpendicular to the normal at texel \(row 0, col 6\): t·n = 0\.1"),
    ("rho_s", lambda a: None, None),
])
def test_validation_errors(field, fn, msg):
    f = _with(field, fn)
    if msg is None:
        SVBRDFMaps(**f)
        return
    with pytest.raises(SampleError, match=msg) as e:
        SVBRDFMaps(**f)
    assert e.value.field == field


@pytest.mark.parametrize("over, msg", [
    (dict(rho_d=np.zeros((8, 8))), r"rho_d: expected shape \(H, W, 3\), got \(8, 8\)"),
    (dict(rho_d=np.zeros((8, 6, 3))), r"H must equal W; got 8 x 6"),
    (dict(rho_s=np.zeros((8, 8, 4))), r"rho_s: expected shape \(8, 8, 3\) \(like rho_d\), got \(8, 8, 4\)"),
    (dict(alpha=np.full((8, 8, 3), 0.1)), r"alpha: expected shape \(8, 8, 2\)"),
    (dict(normal=np.zeros((4, 4, 3))), r"normal: expected shape \(8, 8, 3\)"),
    (dict(transparency=np.zeros((8, 8, 1))), r"transparency: expected shape \(8, 8\)"),
    (dict(rho_d="grey"), r"rho_d: not a numeric array"),
    (dict(size_mm=0.0), r"size_mm: 0 mm is outside \(0, 150\]"),
    (dict(size_mm=150.5), r"size_mm: 150\.5 mm is outside \(0, 150\]"),
    (dict(size_mm=float("nan")), r"size_mm: nan mm is outside"),
    (dict(size_mm="120"), r"size_mm: expected a number of millimetres"),
    (dict(name=""), r"name: expected a non-empty string"),
])
def test_shape_and_scalar_errors(over, msg):
    with pytest.raises(SampleError, match=msg):
        SVBRDFMaps(**_fields(**over))


def test_size_limits_are_inclusive():
    assert SVBRDFMaps(**_fields(size_mm=150)).size_mm == 150.0
    assert isinstance(SVBRDFMaps(**_fields(size_mm=np.float32(20))).size_mm, float)


# --- orientation -------------------------------------------------------------------------------------


def test_texel_positions_follow_the_reference_orientation():
    n, size = 8, 100.0
    plane = SamplePlane()
    m = SVBRDFMaps(**_fields(n, size_mm=size))
    p = texel_positions(m, plane)
    assert p.shape == (n, n, 3) and p.dtype == np.float64
    # texel (0, 0) at minimum x and y; column j along +x, row i along +y; on z = -122
    np.testing.assert_allclose(p[0, 0], [-50 + 6.25, -50 + 6.25, -122.0])
    np.testing.assert_allclose(p[0, n - 1], [50 - 6.25, -50 + 6.25, -122.0])
    np.testing.assert_allclose(p[n - 1, 0], [-50 + 6.25, 50 - 6.25, -122.0])
    np.testing.assert_allclose(p[3, 5], [-50 + 5.5 * 12.5, -50 + 3.5 * 12.5, -122.0])
    np.testing.assert_allclose(np.diff(p[..., 0], axis=1), 12.5)
    np.testing.assert_allclose(np.diff(p[..., 0], axis=0), 0.0)
    np.testing.assert_allclose(np.diff(p[..., 1], axis=0), 12.5)
    np.testing.assert_allclose(p.mean(axis=(0, 1)), plane.origin, atol=1e-12)  # centred on the origin


def test_a_map_that_depends_on_world_x_only_stays_so():
    """ρd written as a function of world x through texel_positions reads back as one: every texel with
    the same world x has the same ρd, whatever its y, and a texel's world x reproduces its value."""
    plane = SamplePlane()
    m0 = SVBRDFMaps(**_fields(16, size_mm=120.0))
    x = texel_positions(m0, plane)[..., 0]
    g = lambda xx: (xx + 60.0) / 120.0  # noqa: E731
    m = dataclasses.replace(m0, rho_d=np.repeat(g(x)[..., None], 3, axis=2))
    p = texel_positions(m, plane)
    np.testing.assert_allclose(m.rho_d[..., 0], g(p[..., 0]), atol=1e-7)
    assert np.all(m.rho_d == m.rho_d[:1])  # constant along y (rows)
    assert np.all(np.diff(m.rho_d[..., 0], axis=1) > 0)  # increasing with x (columns)
    rc = world_to_texel(m, plane, [[50.0, -10.0, -122.0], [50.0, 33.0, -122.0]])
    cols = np.rint(rc[:, 1]).astype(int)
    assert cols[0] == cols[1] == 14
    np.testing.assert_allclose(m.rho_d[np.rint(rc[:, 0]).astype(int), cols, 0], g(p[0, 14, 0]))


@pytest.mark.parametrize("plane", [
    SamplePlane(),
    SamplePlane(origin=(3.0, -7.0, -120.0), x_axis=(np.cos(0.3), np.sin(0.3), 0.0)),
    SamplePlane(origin=(1.0, 2.0, 3.0), normal=(0.0, -np.sin(0.2), np.cos(0.2)),
                x_axis=(1.0, 0.0, 0.0)),
])
def test_world_to_texel_inverts_texel_positions(plane):
    m = SVBRDFMaps(**_fields(10, size_mm=80.0))
    p = texel_positions(m, plane)
    rc = world_to_texel(m, plane, p)
    ii, jj = np.meshgrid(np.arange(10), np.arange(10), indexing="ij")
    np.testing.assert_allclose(rc[..., 0], ii, atol=1e-9)
    np.testing.assert_allclose(rc[..., 1], jj, atol=1e-9)
    # the sample's corners are the outer texel edges; a point off the plane projects along its normal
    o, xa, ya = np.array(plane.origin), np.array(plane.x_axis), plane.y_axis
    np.testing.assert_allclose(world_to_texel(m, plane, o - 40 * xa - 40 * ya), [-0.5, -0.5], atol=1e-9)
    np.testing.assert_allclose(world_to_texel(m, plane, o + 40 * xa + 40 * ya + 7 * np.array(plane.normal)),
                               [9.5, 9.5], atol=1e-9)
    np.testing.assert_allclose(world_to_texel(m, plane, o), [4.5, 4.5], atol=1e-9)


def test_sample_larger_than_the_plane_is_refused():
    m = SVBRDFMaps(**_fields(size_mm=120.0))
    with pytest.raises(SampleError, match="120 mm wide; the rig's sample plane takes at most 100 mm"):
        texel_positions(m, SamplePlane(max_size=100.0))
    with pytest.raises(ValueError, match=r"xyz must have shape \(\.\.\., 3\)"):
        world_to_texel(m, SamplePlane(), [1.0, 2.0])


# --- folder I/O --------------------------------------------------------------------------------------


def test_write_read_round_trip(tmp_path):
    m = _random_maps()
    d = write_maps(m, tmp_path / "maps")
    assert sorted(p.name for p in d.iterdir()) == sorted([*MAP_FILES.values(), "sample.toml"])
    r = read_maps(d)
    assert (r.name, r.size_mm, r.shape) == ("random", 90.0, (12, 12))
    for k in ("rho_d", "rho_s", "alpha", "transparency"):
        assert getattr(r, k).tobytes() == getattr(m, k).tobytes(), k  # float32, bit-exact
    np.testing.assert_allclose(r.normal, m.normal, atol=2e-7)  # only float32 rounding of n·0.5 + 0.5
    np.testing.assert_allclose(r.tangent, m.tangent, atol=2e-7)
    # the files follow the contract literally
    np.testing.assert_array_equal(read_rgb_exr(d / "normal_texture.exr"),
                                  m.normal * np.float32(0.5) + np.float32(0.5))
    ax = read_rgb_exr(d / "ax_ay_texture.exr")
    np.testing.assert_array_equal(ax[..., :2], m.alpha)
    np.testing.assert_array_equal(ax[..., 2], 0.0)
    beta = read_rgb_exr(d / "transparency_texture.exr")
    np.testing.assert_array_equal(beta, np.repeat(m.transparency[..., None], 3, axis=2))
    assert read_exr_attributes(d / "pd_texture.exr")["hemicube_sample"] == "random"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_write_refuses_existing_folder_unless_overwrite(tmp_path):
    a, b = SVBRDFMaps(**_fields(name="a")), SVBRDFMaps(**_fields(name="b", size_mm=40.0))
    d = write_maps(a, tmp_path / "s")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_maps(b, d)
    write_maps(b, d, overwrite=True)
    assert (read_maps(d).name, read_maps(d).size_mm) == ("b", 40.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_failed_write_leaves_no_half_written_folder(tmp_path, monkeypatch):
    old = write_maps(SVBRDFMaps(**_fields(name="old")), tmp_path / "s")
    calls = []

    def flaky(path, rgb, **kw):
        calls.append(path)
        if len(calls) % 6 == 3:  # fail on the third file of each write
            raise OSError("disk full")
        return write_rgb_exr(path, rgb, **kw)

    monkeypatch.setattr(samples, "write_rgb_exr", flaky)
    with pytest.raises(OSError, match="disk full"):
        write_maps(SVBRDFMaps(**_fields(name="new")), old, overwrite=True)
    with pytest.raises(OSError, match="disk full"):
        write_maps(SVBRDFMaps(**_fields(name="new")), tmp_path / "fresh")
    monkeypatch.undo()
    assert read_maps(old).name == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # no temp folder, no "fresh"


def _folder(tmp_path, maps=None):
    return write_maps(maps or SVBRDFMaps(**_fields(n=6)), tmp_path / "m")


def test_nan_in_a_map_file_names_the_file(tmp_path):
    d = _folder(tmp_path)
    img = read_rgb_exr(d / "pd_texture.exr")
    img[2, 3, 1] = np.nan
    write_rgb_exr(d / "pd_texture.exr", img)
    with pytest.raises(SampleError, match=r"pd_texture\.exr: non-finite value nan at pixel \(row 2, col 3\)"):
        read_maps(d)


@pytest.mark.parametrize("fname, channel, value, msg", [
    ("ps_texture.exr", 0, 25.0, r"ps_texture\.exr: rho_s: value \(25, 2, 2\) at texel \(row 1, col 4\) is outside \[0, 20\]"),
    ("ax_ay_texture.exr", 1, 0.0, r"ax_ay_texture\.exr: alpha: value \(0\.2, 0\) at texel \(row 1, col 4\)"),
    ("pd_texture.exr", 2, -0.5, r"pd_texture\.exr: rho_d: .* at texel \(row 1, col 4\) is outside \[0, 1\]"),
    ("transparency_texture.exr", None, 2.0, r"transparency_texture\.exr: transparency: value 2 at texel \(row 1, col 4\)"),
    ("normal_texture.exr", None, 0.5, r"normal_texture\.exr: texel \(row 1, col 4\) decodes to \(0, 0, 0\), "
                                      r"length 0, not a unit normal"),
    ("normal_texture.exr", 2, 0.1, r"normal_texture\.exr: texel \(row 1, col 4\) decodes to \(0, 0, -0\.8\)"),
    ("tangent_texture.exr", 0, 1.5, r"tangent_texture\.exr: texel \(row 1, col 4\) decodes to \(2, 0, 0\)"),
    ("tangent_texture.exr", None, (0.5, 0.5, 1.0), r"tangent_texture\.exr: the tangent at texel \(row 1, col 4\) "
                                                   r"is parallel to the normal"),
])
def test_bad_values_in_a_map_file_name_the_file(tmp_path, fname, channel, value, msg):
    d = _folder(tmp_path)
    img = read_rgb_exr(d / fname)
    if channel is None:
        img[1, 4] = value
    else:
        img[1, 4, channel] = value
    write_rgb_exr(d / fname, img)
    with pytest.raises(SampleError, match=msg):
        read_maps(d)


def test_downward_normal_in_file(tmp_path):
    d = _folder(tmp_path)
    img = read_rgb_exr(d / "normal_texture.exr")
    img[0, 0] = (0.5, 0.5, 0.0)  # n = (0, 0, -1)
    write_rgb_exr(d / "normal_texture.exr", img)
    with pytest.raises(SampleError, match=r"normal_texture\.exr: normal: \(0, 0, -1\) at texel \(row 0, col 0\) "
                                          r"is not in the upper hemisphere"):
        read_maps(d)


def test_missing_files_and_folders(tmp_path):
    with pytest.raises(SampleError, match="not a map folder \\(no such directory\\)"):
        read_maps(tmp_path / "none")
    d = _folder(tmp_path)
    (d / "tangent_texture.exr").unlink()
    (d / "ps_texture.exr").unlink()
    with pytest.raises(SampleError, match=r"not a map folder: missing ps_texture\.exr, tangent_texture\.exr"):
        read_maps(d)


def test_wrong_size_and_corrupt_file(tmp_path):
    d = _folder(tmp_path)
    write_rgb_exr(d / "ps_texture.exr", np.ones((5, 6, 3)))
    with pytest.raises(SampleError, match=r"ps_texture\.exr: image is 5 x 6 \(H x W\); expected 6 x 6"):
        read_maps(d)
    (d / "ps_texture.exr").write_bytes(b"garbage")
    with pytest.raises(SampleError, match=r"ps_texture\.exr: not an OpenEXR file"):
        read_maps(d)


def test_optional_transparency_and_toml(tmp_path):
    m = SVBRDFMaps(**_fields(n=6, transparency=np.full((6, 6), 0.3), size_mm=70.0, name="x"))
    d = write_maps(m, tmp_path / "third_party")
    (d / "transparency_texture.exr").unlink()
    (d / "sample.toml").unlink()
    r = read_maps(d)
    np.testing.assert_array_equal(r.transparency, 0.0)  # default: opaque
    assert (r.size_mm, r.name) == (150.0, "third_party")  # defaults: 150 mm, the folder's name
    assert read_maps(d, size_mm=33.0).size_mm == 33.0
    with pytest.raises(SampleError, match=r"sample\.toml: size_mm: 200 mm is outside"):
        read_maps(d, size_mm=200.0)
    (d / "sample.toml").write_text('name = "given"\nsize_mm = 44.5\n')
    assert (read_maps(d).name, read_maps(d).size_mm) == ("given", 44.5)
    assert read_maps(d, size_mm=10).size_mm == 10.0  # the argument wins
    (d / "sample.toml").write_text("size_mm = [")
    with pytest.raises(SampleError, match=r"sample\.toml: not valid TOML"):
        read_maps(d)
    (d / "sample.toml").write_text('format = "hemicube-rig"\n')
    with pytest.raises(SampleError, match=r"sample\.toml: format must be 'hemicube-sample'"):
        read_maps(d)
    (d / "sample.toml").write_text('size_mm = "big"\n')
    with pytest.raises(SampleError, match=r"sample\.toml: size_mm must be a number"):
        read_maps(d)


def test_third_party_8bit_quantised_normals_are_renormalised(tmp_path):
    """Maps that went through 8-bit rounding (e.g. from PNG): n and t are no longer unit nor orthogonal;
    reading renormalises and re-orthogonalises, staying within the rounding of the originals."""
    m = _random_maps(n=16, seed=5)
    d = write_maps(m, tmp_path / "q")
    for f in ("normal_texture.exr", "tangent_texture.exr"):
        write_rgb_exr(d / f, np.round(read_rgb_exr(d / f) * 255) / 255)
    raw_n = np.round((m.normal * 0.5 + 0.5) * 255) / 255 * 2 - 1
    assert np.abs(np.linalg.norm(raw_n, axis=-1) - 1).max() > 1e-3  # the raw data would fail validation
    r = read_maps(d)
    np.testing.assert_allclose(np.linalg.norm(r.normal, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(r.tangent, axis=-1), 1.0, atol=1e-6)
    assert np.abs(np.sum(r.normal * r.tangent, -1)).max() < 1e-6
    assert np.abs(r.normal - m.normal).max() < 0.01
    assert np.abs(r.tangent - m.tangent).max() < 0.02


def test_half_float_third_party_maps_are_accepted(tmp_path):
    m = _random_maps(n=8, seed=6)
    d = write_maps(m, tmp_path / "h")
    for f in MAP_FILES.values():
        write_rgb_exr(d / f, read_rgb_exr(d / f), half=True)
    r = read_maps(d)
    np.testing.assert_allclose(r.rho_s, m.rho_s, rtol=1e-3)
    np.testing.assert_allclose(r.normal, m.normal, atol=2e-3)


# --- canonical anisotropy ----------------------------------------------------------------------------


def _brdf_of(maps, rows, cols, wi, wo):
    from twin.optics.ggx import brdf

    return brdf(wi, wo, maps.normal[rows, cols], maps.tangent[rows, cols], maps.rho_d[rows, cols],
                maps.rho_s[rows, cols], maps.alpha[rows, cols, 0], maps.alpha[rows, cols, 1])


def _hemisphere_dirs(rng, normal):
    v = rng.standard_normal(normal.shape)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(np.sum(v * normal, -1, keepdims=True) < 0, -v, v)


def test_canonical_anisotropy_swaps_and_preserves_the_brdf():
    m = _random_maps(n=12, seed=7)
    c = canonical_anisotropy(m)
    swapped = m.alpha[..., 0] < m.alpha[..., 1]
    assert 20 < swapped.sum() < 124  # both cases present
    assert np.all(c.alpha[..., 0] >= c.alpha[..., 1])
    np.testing.assert_array_equal(c.alpha[swapped], m.alpha[swapped][:, ::-1])
    np.testing.assert_array_equal(c.alpha[~swapped], m.alpha[~swapped])
    np.testing.assert_array_equal(c.tangent[~swapped], m.tangent[~swapped])
    np.testing.assert_allclose(c.tangent[swapped], np.cross(m.normal, m.tangent)[swapped], atol=1e-6)
    np.testing.assert_array_equal(c.normal, m.normal)
    # the rendered BRDF is the same for several directions per texel
    rng = np.random.default_rng(8)
    rows, cols = np.nonzero(np.ones((12, 12), bool))
    rows, cols = np.repeat(rows, 4), np.repeat(cols, 4)
    n = m.normal[rows, cols].astype(np.float64)
    wi, wo = _hemisphere_dirs(rng, n), _hemisphere_dirs(rng, n)
    # add near-mirror pairs, where the specular lobe (and so the roughness axes) matters most
    wo[::4] = 2 * np.sum(wi[::4] * n[::4], -1, keepdims=True) * n[::4] - wi[::4]
    wo[::4] = _hemisphere_dirs(rng, n[::4]) * 0.05 + wo[::4]
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    wo = np.where(np.sum(wo * n, -1, keepdims=True) > 0.05, wo, n)
    f0, f1 = _brdf_of(m, rows, cols, wi, wo), _brdf_of(c, rows, cols, wi, wo)
    assert f0[swapped[rows, cols]].max() > 1.0  # some real specular peaks among the swapped texels
    np.testing.assert_allclose(f1, f0, rtol=2e-5, atol=1e-7)
    # and an isotropic BRDF would not have passed: the swap matters, the test is sensitive
    iso = dataclasses.replace(m, alpha=m.alpha[..., ::-1])
    assert np.abs(_brdf_of(iso, rows, cols, wi, wo) - f0).max() > 0.1


def test_canonical_anisotropy_is_a_no_op_when_already_canonical():
    m = builtin_sample("brushed_metal", 16)
    assert canonical_anisotropy(m) is m
    c = canonical_anisotropy(builtin_sample("satin_weave", 32))
    assert canonical_anisotropy(c) is c


def test_satin_canonical_keeps_brdf_on_builtin():
    m = builtin_sample("satin_weave", 32)
    c = canonical_anisotropy(m)
    assert np.all(c.alpha_x >= c.alpha_y) and np.all(m.alpha_x < m.alpha_y)
    rows, cols = np.array([0, 5, 17, 31, 12]), np.array([3, 9, 20, 31, 0])
    n = m.normal[rows, cols].astype(np.float64)
    wi = np.array([[0.3, 0.2, 0.93], [0.0, 0.6, 0.8], [-0.5, 0.1, 0.86], [0.2, -0.3, 0.93], [0.6, 0.0, 0.8]])
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo = 2 * np.sum(wi * n, -1, keepdims=True) * n - wi + np.array([0.05, -0.03, 0.0])
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    np.testing.assert_allclose(_brdf_of(c, rows, cols, wi, wo), _brdf_of(m, rows, cols, wi, wo), rtol=2e-5)


# --- built-in samples --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", BUILTIN_SAMPLES)
def test_builtin_basics(name):
    m = builtin_sample(name, RES)
    assert isinstance(m, SVBRDFMaps)
    assert m.shape == (RES, RES) and m.size_mm == 120.0 and m.name == name
    assert m.rho_d.shape == (RES, RES, 3) and m.alpha.shape == (RES, RES, 2) and m.transparency.shape == (RES, RES)
    again = builtin_sample(name, RES)
    for k in SVBRDFMaps.ARRAYS:
        assert getattr(again, k).tobytes() == getattr(m, k).tobytes(), k
    other = builtin_sample(name, RES, seed=1)
    differs = any(getattr(other, k).tobytes() != getattr(m, k).tobytes() for k in SVBRDFMaps.ARRAYS)
    assert differs == (name != "ramps")  # ramps has no noise
    assert builtin_sample(name, 17).shape == (17, 17)  # any integer >= 16
    assert builtin_sample(name, 16, size_mm=50.0).size_mm == 50.0


@pytest.mark.parametrize("res, msg", [
    (15, r"resolution must be in \[16, 8192\], got 15"),
    (16.0, "resolution must be an integer >= 16, got 16.0"),
    (True, "resolution must be an integer"),
    ("64", "resolution must be an integer"),
])
def test_builtin_resolution_errors(res, msg):
    with pytest.raises(SampleError, match=msg):
        builtin_sample("ramps", res)


def test_builtin_other_errors():
    with pytest.raises(SampleError, match="unknown built-in sample 'velvet'; expected one of ramps, "
                                          "brushed_metal, satin_weave"):
        builtin_sample("velvet")
    with pytest.raises(SampleError, match="seed must be a non-negative integer"):
        builtin_sample("satin_weave", 16, seed=-1)
    assert builtin_sample("ramps", np.int64(20)).shape == (20, 20)


def _region(m, name):
    rs, cs = ramp_regions(m.resolution)[name]
    return {k: getattr(m, k)[rs, cs] for k in SVBRDFMaps.ARRAYS}


def _assert_reference(values, skip=()):
    ref = RAMPS_REFERENCE
    for k in ("rho_d", "rho_s", "alpha", "normal", "tangent", "transparency"):
        if k not in skip:
            np.testing.assert_allclose(values[k], np.broadcast_to(np.float32(ref[k]), values[k].shape),
                                       atol=1e-7, err_msg=k)


@pytest.mark.parametrize("res", [16, RES, 128])
def test_ramps_regions_hold_the_promised_ramps(res):
    m = builtin_sample("ramps", res)
    regions = ramp_regions(res)
    assert len(regions) == 8
    b = samples.ramp_border(res)
    for k, (rs, cs) in regions.items():
        assert rs.stop - rs.start >= 2 and cs.stop - cs.start >= 6, k
        for name, a in _region(m, k).items():  # every parameter is constant along y (rows)
            assert np.all(a == a[:1]), (k, name)
    # borders (everything outside the interiors) hold the plain reference values
    inside = np.zeros((res, res), bool)
    for rs, cs in regions.values():
        inside[rs, cs] = True
    assert (~inside).sum() >= 4 * b * res
    _assert_reference({k: getattr(m, k)[~inside] for k in SVBRDFMaps.ARRAYS})

    r = _region(m, "rho_d_grey")
    s = np.linspace(0, 1, r["rho_d"].shape[1])
    np.testing.assert_allclose(r["rho_d"][0], np.stack([s] * 3, -1), atol=1e-7)
    assert r["rho_d"][0, 0, 0] == 0 and r["rho_d"][0, -1, 0] == 1
    _assert_reference(r, skip=("rho_d",))

    r = _region(m, "rho_d_colour")
    np.testing.assert_allclose(r["rho_d"][0, -1], [1.0, 0.55, 0.2], atol=1e-7)
    np.testing.assert_allclose(r["rho_d"][0, :, 1] / 0.55, np.linspace(0, 1, r["rho_d"].shape[1]), atol=1e-6)
    _assert_reference(r, skip=("rho_d",))

    r = _region(m, "rho_s")
    np.testing.assert_allclose(r["rho_s"][0, :, 0], 10 * np.linspace(0, 1, r["rho_s"].shape[1]), atol=1e-6)
    _assert_reference(r, skip=("rho_s",))

    r = _region(m, "alpha_iso")
    ax = r["alpha"][0, :, 0]
    assert ax[0] == np.float32(0.006) and ax[-1] == np.float32(0.5)  # spans exactly 0.006..0.5
    assert np.all(np.diff(ax) > 0)  # strictly monotonic
    np.testing.assert_allclose(np.diff(np.log(ax.astype(np.float64))), np.log(0.5 / 0.006) / (ax.size - 1), rtol=1e-5)
    np.testing.assert_array_equal(r["alpha"][..., 0], r["alpha"][..., 1])  # isotropic
    _assert_reference(r, skip=("alpha",))

    r = _region(m, "anisotropy")
    np.testing.assert_array_equal(r["alpha"][..., 0], np.float32(0.3))
    ay = r["alpha"][0, :, 1]
    assert ay[0] == np.float32(0.3) and ay[-1] == np.float32(0.02) and np.all(np.diff(ay) < 0)
    assert ax.max() / ay.min() > 10  # strongly anisotropic at the end
    _assert_reference(r, skip=("alpha",))

    r = _region(m, "normal_tilt")
    n = r["normal"][0].astype(np.float64)
    tilt = _tilt_deg(n)
    np.testing.assert_allclose(tilt, 40 * np.linspace(0, 1, n.shape[0]), atol=1e-4)
    np.testing.assert_array_equal(n[:, 0], 0.0)  # rotated about the tangent axis t = +x
    assert np.all(n[1:, 1] < 0)  # +z rotated about +x: towards -y
    _assert_reference(r, skip=("normal",))

    r = _region(m, "tangent_rotation")
    t = r["tangent"][0].astype(np.float64)
    ang = np.degrees(np.arctan2(t[:, 1], t[:, 0]))
    np.testing.assert_allclose(ang, 180 * np.linspace(0, 1, t.shape[0]), atol=1e-4)
    np.testing.assert_array_equal(r["alpha"], np.broadcast_to(np.float32([0.3, 0.05]), r["alpha"].shape))
    _assert_reference(r, skip=("tangent", "alpha"))

    r = _region(m, "transparency")
    np.testing.assert_allclose(r["transparency"][0], np.linspace(0, 1, r["transparency"].shape[1]), atol=1e-7)
    _assert_reference(r, skip=("transparency",))


def test_ramps_layout_in_world_coordinates():
    """The documented layout: the ρd ramps at the lowest y, transparency at the highest y and +x side."""
    m = builtin_sample("ramps", RES)
    p = texel_positions(m, SamplePlane())
    (rs, cs) = ramp_regions(RES)["rho_d_grey"]
    assert p[rs, cs, 1].max() < -30 and p[rs, cs, 0].max() < 0
    (rs, cs) = ramp_regions(RES)["transparency"]
    assert p[rs, cs, 1].min() > 30 and p[rs, cs, 0].min() > 0
    # along a ramp, the parameter grows with world x
    rs, cs = ramp_regions(RES)["rho_s"]
    x, v = p[rs.start, cs, 0], m.rho_s[rs.start, cs, 0]
    assert np.all(np.diff(x) > 0) and np.all(np.diff(v) > 0)


def test_brushed_metal_properties():
    m = builtin_sample("brushed_metal", 128)
    assert np.all(np.abs(m.rho_d - 0.02) <= 0.0050001)
    assert 4.0 <= m.rho_s.min() and m.rho_s.max() <= 6.0
    assert m.rho_s.std() > 0.1  # streak noise
    ax, ay = m.alpha_x.astype(np.float64), m.alpha_y.astype(np.float64)
    assert 0.25 - 1e-6 <= ax.min() and ax.max() <= 0.35 + 1e-6
    assert 0.02 - 1e-6 <= ay.min() and ay.max() <= 0.04 + 1e-6
    assert np.mean(ax / ay) >= 5 and np.min(ax / ay) >= 5
    tilt = _tilt_deg(m.normal.astype(np.float64))
    assert tilt.max() < 3.0 and tilt.mean() > 0.2  # micro normal perturbation, present but < 3°
    t = m.tangent.astype(np.float64)
    assert np.abs(t[..., 2]).max() < 0.05  # brushing runs in the plane
    doubled = np.exp(2j * np.arctan2(t[..., 1], t[..., 0]))  # axial direction (modulo 180°) as a phasor
    axial = np.angle(doubled * np.conj(doubled.mean())) / 2  # about the mean direction: no wrap-around
    spread = np.degrees(axial.max() - axial.min())
    assert 10 < spread < 90  # the brush direction curves, but slowly
    txy = t[..., :2] / np.linalg.norm(t[..., :2], axis=-1, keepdims=True)  # in-plane direction (the tangent
    step = np.degrees(np.arccos(np.clip(np.abs(np.sum(txy[:, 1:] * txy[:, :-1], -1)), 0, 1)))  # also tilts
    assert step.max() < 2.0  # smooth from texel to texel                   # with the micro normal, < 2.5°)
    # fine detail: the streak noise changes at the texel scale across the streaks
    across = np.abs(np.diff(m.rho_s[..., 0].astype(np.float64), axis=0)).mean()
    assert across > 0.05
    assert np.all(m.transparency == 0)


def test_satin_weave_properties():
    res = 128
    m = builtin_sample("satin_weave", res)
    p = samples.satin_thread_texels(res)
    assert 4 <= p <= 8
    assert m.transparency.max() > 0.2 and 0 < np.mean(m.transparency > 0) < 0.1  # small gaps only
    gaps = np.argwhere(m.transparency > 0)
    assert np.all(gaps % p == p - 1)  # the gaps sit at thread corners
    t = m.tangent.astype(np.float64)
    warp = np.abs(t[..., 1]) > 0.95
    weft = np.abs(t[..., 0]) > 0.95
    assert np.all(warp ^ weft)  # every texel in exactly one of the two families
    assert 0.6 < warp.mean() < 0.9 and weft.mean() > 0.1  # warp-faced satin: mostly warp on top
    np.testing.assert_array_equal(warp, samples.satin_warp_on_top(res))
    # the two families are orthogonal (their mean directions, modulo sign)
    mw = np.abs(t[warp]).mean(0)
    mf = np.abs(t[weft]).mean(0)
    assert abs(np.dot(mw / np.linalg.norm(mw), mf / np.linalg.norm(mf))) < 0.05
    # threads change colour between warp and weft
    assert abs(m.rho_d[warp, 1].mean() - m.rho_d[weft, 1].mean()) > 0.2
    # anisotropic roughness, smaller along the thread (the tangent)
    assert np.all(m.alpha_x < m.alpha_y)
    assert 0.13 < m.alpha_x.mean() < 0.17 and 0.36 < m.alpha_y.mean() < 0.44
    tilt = _tilt_deg(m.normal.astype(np.float64))
    assert 10 < tilt.max() <= 15.001  # bumps at crossings, up to ~15°
    # thread-sized features: each cell's dome repeats with the thread period
    assert np.abs(m.normal[:, :, 0][:, p // 2::p]).max() < np.abs(m.normal[:, :, 0]).max()


def test_builtins_survive_the_folder_round_trip(tmp_path):
    for name in BUILTIN_SAMPLES:
        m = builtin_sample(name, 32)
        r = read_maps(write_maps(m, tmp_path / name))
        assert (r.name, r.size_mm) == (name, 120.0)
        for k in ("rho_d", "rho_s", "alpha", "transparency"):
            assert getattr(r, k).tobytes() == getattr(m, k).tobytes(), (name, k)
        np.testing.assert_allclose(r.normal, m.normal, atol=2e-7)
        np.testing.assert_allclose(r.tangent, m.tangent, atol=2e-7)


def test_load_sample(tmp_path, monkeypatch):
    m = load_sample("satin_weave", resolution=24)
    assert m.shape == (24, 24) and m.name == "satin_weave"
    d = write_maps(builtin_sample("ramps", 16), tmp_path / "folder")
    assert load_sample(d).name == "ramps"
    assert load_sample(str(d)).shape == (16, 16)
    with pytest.raises(SampleError, match=r"'velvet' is neither a built-in sample \(ramps, brushed_metal, "
                                          r"satin_weave, satin, .*, quadrants\) nor an existing map folder"):
        load_sample("velvet")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SampleError, match="not a map folder: missing pd_texture.exr"):
        load_sample(tmp_path / "empty")
    monkeypatch.chdir(tmp_path)
    os.mkdir("ramps")  # a folder named like a built-in does not shadow it
    assert load_sample("ramps", resolution=16).name == "ramps"
