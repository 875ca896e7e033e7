"""twin.camera.bayer: PFNC BayerRG12 / BayerRG12p byte layouts (against hand-worked bytes), CFA layouts,
bilinear demosaicing and Malvar-He-Cutler (2004) demosaicing (against colour-demosaicing as the oracle)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.camera.bayer import (DEMOSAICS, cfa_index, cfa_table, demosaic, from_bayer_rg12, malvar2004, mosaic,
                               pack_bayer_rg12p, pfnc_name, to_bayer_rg12, unpack_bayer_rg12p)

with warnings.catch_warnings():
    # colour-demosaicing 0.2.7 imports convolve from scipy.ndimage.filters, deprecated since SciPy 1.8
    warnings.simplefilter("ignore", DeprecationWarning)
    from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004


# --- BayerRG12p: hand-worked bytes ----------------------------------------------------------------
@pytest.mark.parametrize("p0, p1, expected", [
    (0x123, 0xABC, bytes([0x23, 0xC1, 0xAB])),
    (0xFFF, 0x000, bytes([0xFF, 0x0F, 0x00])),
    (0x001, 0x800, bytes([0x01, 0x00, 0x80])),
    (0x000, 0xFFF, bytes([0x00, 0xF0, 0xFF])),
    (0x456, 0x789, bytes([0x56, 0x94, 0x78])),
])
def test_rg12p_pair(p0, p1, expected):
    raw = np.array([[p0, p1]], dtype=np.uint16)
    assert pack_bayer_rg12p(raw) == expected
    assert unpack_bayer_rg12p(expected, 1, 2).tolist() == [[p0, p1]]


def test_rg12p_2x4_frame_end_to_end():
    raw = np.array([[0x123, 0xABC, 0xFFF, 0x000],
                    [0x001, 0x800, 0x456, 0x789]], dtype=np.uint16)
    expected = bytes([0x23, 0xC1, 0xAB, 0xFF, 0x0F, 0x00,   # row 0: (123, ABC), (FFF, 000)
                      0x01, 0x00, 0x80, 0x56, 0x94, 0x78])  # row 1: (001, 800), (456, 789)
    data = pack_bayer_rg12p(raw)
    assert data == expected
    back = unpack_bayer_rg12p(data, 2, 4)
    assert back.dtype == np.uint16 and back.shape == (2, 4)
    np.testing.assert_array_equal(back, raw)
    # unpacking accepts any bytes-like object
    np.testing.assert_array_equal(unpack_bayer_rg12p(bytearray(data), 2, 4), raw)
    np.testing.assert_array_equal(unpack_bayer_rg12p(np.frombuffer(data, np.uint8), 2, 4), raw)


def test_rg12_unpacked_hand_worked():
    raw = np.array([[0x123, 0xABC], [0xFFF, 0x000]], dtype=np.uint16)
    data = to_bayer_rg12(raw)
    assert data == bytes([0x23, 0x01, 0xBC, 0x0A, 0xFF, 0x0F, 0x00, 0x00])  # little-endian, LSB-aligned
    np.testing.assert_array_equal(from_bayer_rg12(data, 2, 2), raw)


@settings(max_examples=60, deadline=None)
@given(h=st.integers(1, 9), half_w=st.integers(1, 9), seed=st.integers(0, 2**32 - 1))
def test_round_trips_random_frames(h, half_w, seed):
    raw = np.random.default_rng(seed).integers(0, 4096, size=(h, 2 * half_w), dtype=np.uint16)
    packed = pack_bayer_rg12p(raw)
    assert len(packed) == 3 * raw.size // 2
    np.testing.assert_array_equal(unpack_bayer_rg12p(packed, h, 2 * half_w), raw)
    plain = to_bayer_rg12(raw)
    assert len(plain) == 2 * raw.size
    np.testing.assert_array_equal(from_bayer_rg12(plain, h, 2 * half_w), raw)


@settings(max_examples=40, deadline=None)
@given(data=st.binary(min_size=6, max_size=6 * 8).filter(lambda b: len(b) % 6 == 0))
def test_packed_bytes_round_trip(data):
    """Every byte string is a valid 12p stream: unpack then pack gives the same bytes."""
    n = len(data) // 3 * 2
    assert pack_bayer_rg12p(unpack_bayer_rg12p(data, 1, n)) == data


# --- errors ---------------------------------------------------------------------------------------
def test_errors():
    good = np.zeros((2, 4), np.uint16)
    with pytest.raises(ValueError, match="even width"):
        pack_bayer_rg12p(np.zeros((2, 3), np.uint16))
    with pytest.raises(ValueError, match="even width"):
        unpack_bayer_rg12p(bytes(9), 2, 3)
    over = good.copy()
    over[1, 2] = 4096
    for f in (pack_bayer_rg12p, to_bayer_rg12):
        with pytest.raises(ValueError, match="12 bits"):
            f(over)
        with pytest.raises(TypeError, match="uint16"):
            f(good.astype(np.int32))
        with pytest.raises(ValueError, match="2-D"):
            f(np.zeros((2, 2, 2), np.uint16))
        with pytest.raises(TypeError, match="numpy array"):
            f([[1, 2]])
    with pytest.raises(ValueError, match="needs 12 bytes, got 11"):
        unpack_bayer_rg12p(bytes(11), 2, 4)
    with pytest.raises(ValueError, match="needs 16 bytes, got 18"):
        from_bayer_rg12(bytes(18), 2, 4)
    with pytest.raises(ValueError, match="upper 4 bits"):
        from_bayer_rg12(bytes([0, 0, 0x00, 0x10]), 1, 2)
    with pytest.raises(ValueError, match="positive integer"):
        from_bayer_rg12(bytes(0), 0, 2)
    with pytest.raises(TypeError, match="bytes-like"):
        unpack_bayer_rg12p("abc", 1, 2)


def test_pfnc_names():
    assert pfnc_name("RG", 12, packed=True) == "BayerRG12p"
    assert pfnc_name("BG", 12) == "BayerBG12"
    with pytest.raises(ValueError):
        pfnc_name("XY")


# --- CFA and demosaicing --------------------------------------------------------------------------
def test_cfa_layouts():
    assert cfa_index("RG", 2, 2).tolist() == [[0, 1], [1, 2]]
    assert cfa_index("GR", 2, 2).tolist() == [[1, 0], [2, 1]]
    assert cfa_index("GB", 2, 2).tolist() == [[1, 2], [0, 1]]
    assert cfa_index("BG", 2, 2).tolist() == [[2, 1], [1, 0]]
    assert cfa_index("RG", 3, 5)[2].tolist() == [0, 1, 0, 1, 0]
    rgb = np.arange(2 * 2 * 3).reshape(2, 2, 3)
    assert mosaic(rgb, "RG").tolist() == [[0, 4], [7, 11]]
    with pytest.raises(ValueError, match="Bayer layout"):
        cfa_index("RGB", 2, 2)


@pytest.mark.parametrize("pattern", ["RG", "GR", "GB", "BG"])
@pytest.mark.parametrize("method, border", [("bilinear", 1), ("malvar2004", 2)])
def test_demosaic_exact_for_constant_and_ramps(pattern, method, border):
    H, W = 9, 12
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    # a constant colour: exact everywhere, borders included, also where the 2-pixel pad wraps a 2- or 3-wide image
    const = np.array([0.3, 1.7, 5.0])
    for h, w in ((H, W), (2, 2), (2, 3), (3, 5)):
        img = np.broadcast_to(const, (h, w, 3))
        np.testing.assert_allclose(demosaic(mosaic(img, pattern), pattern, method), img, rtol=0, atol=1e-12)
    # linear ramps, different per channel: exact away from the border the kernels reach (1 or 2 pixels)
    ramp = np.stack([1.0 + 0.5 * x + 0.25 * y, 3.0 - 0.75 * x + 2.0 * y, -2.0 + 0.125 * x - 1.5 * y], axis=-1)
    out = demosaic(mosaic(ramp, pattern), pattern, method)
    inner = (slice(border, -border), slice(border, -border))
    np.testing.assert_allclose(out[inner], ramp[inner], rtol=0, atol=1e-12)
    # known sites keep their value everywhere; the border is not exact for a ramp (mirrored)
    np.testing.assert_array_equal(mosaic(out, pattern), mosaic(ramp, pattern))
    assert np.abs(out - ramp).max() > 0.1


def test_demosaic_hand_worked_and_dtypes():
    # RG 2x2 cell [[R=4, G=2], [G=6, B=8]], mirrored: every missing value averages equal copies
    raw = np.array([[4.0, 2.0], [6.0, 8.0]])
    out = demosaic(raw, "RG")
    np.testing.assert_allclose(out[..., 0], 4.0)  # the only R site
    np.testing.assert_allclose(out[..., 2], 8.0)  # the only B site
    np.testing.assert_allclose(out[..., 1], [[4.0, 2.0], [6.0, 4.0]])  # G at R/B = mean of 2 + 6
    assert demosaic(raw.astype(np.float32)).dtype == np.float32
    assert demosaic(raw.astype(np.uint16)).dtype == np.float64
    with pytest.raises(ValueError, match=">= 2"):
        demosaic(np.zeros((1, 4)))
    with pytest.raises(ValueError, match="2-D"):
        demosaic(np.zeros((4, 4, 3)))


# --- Malvar-He-Cutler (2004) ----------------------------------------------------------------------
# colour-demosaicing names a layout by the whole 2x2 cell in row-major order; ours by its first row
ORACLE_PATTERNS = {"RG": "RGGB", "GR": "GRBG", "GB": "GBRG", "BG": "BGGR"}


@pytest.mark.parametrize("shape", [(32, 40), (33, 41)])
@pytest.mark.parametrize("pattern", ["RG", "GR", "GB", "BG"])
def test_malvar2004_matches_colour_demosaicing(pattern, shape):
    name = ORACLE_PATTERNS[pattern]
    assert name == "".join("RGB"[c] for c in cfa_table(pattern).ravel())
    raw = np.random.default_rng(20040517).random(shape)
    ours = malvar2004(raw, pattern)
    ref = demosaicing_CFA_Bayer_Malvar2004(raw, name)
    assert ours.shape == ref.shape == shape + (3,)
    # the oracle pads with scipy's "reflect" (edge pixel repeated), which puts wrong-colour sites in the
    # outer two rings; inside them both read only real pixels
    np.testing.assert_allclose(ours[2:-2, 2:-2], ref[2:-2, 2:-2], rtol=0, atol=1e-12)
    # given our border (mirrored about the edge pixel, even pad width so the phase is kept), it agrees everywhere
    ref_padded = demosaicing_CFA_Bayer_Malvar2004(np.pad(raw, 2, mode="reflect"), name)[2:-2, 2:-2]
    np.testing.assert_allclose(ours, ref_padded, rtol=0, atol=1e-12)


def test_malvar2004_less_spill_than_bilinear_at_a_grey_edge():
    """The reason to use it: where the colours move together, the Laplacian correction removes most of the
    bilinear colour fringe."""
    y, x = np.mgrid[0:16, 0:20].astype(np.float64)
    rgb = np.clip(x + 0.4 * y - 12, 0, 1)[..., None] * np.array([0.8, 1.0, 0.6])
    raw = mosaic(rgb, "RG")
    rms = {m: np.sqrt(np.mean((demosaic(raw, "RG", method=m) - rgb)[2:-2, 2:-2] ** 2)) for m in DEMOSAICS}
    assert rms["malvar2004"] < 0.7 * rms["bilinear"]


def test_demosaic_method_dispatch_and_dtypes():
    assert set(DEMOSAICS) == {"bilinear", "malvar2004"}
    raw = np.random.default_rng(7).random((6, 8))
    for pattern in ("RG", "GR", "GB", "BG"):
        np.testing.assert_array_equal(demosaic(raw, pattern, method="malvar2004"), malvar2004(raw, pattern))
        np.testing.assert_array_equal(demosaic(raw, pattern), demosaic(raw, pattern, method="bilinear"))
        np.testing.assert_array_equal(demosaic(raw, pattern), DEMOSAICS["bilinear"](raw, pattern))
    with pytest.raises(ValueError, match="'bilinear', 'malvar2004'"):
        demosaic(raw, method="ahd")
    with pytest.raises(ValueError, match="unknown demosaicing method"):
        demosaic(raw, method=None)
    for f in (malvar2004, lambda r: demosaic(r, method="malvar2004")):
        out32 = f(raw.astype(np.float32))
        assert out32.dtype == np.float32
        np.testing.assert_allclose(out32, malvar2004(raw.astype(np.float32).astype(np.float64)), rtol=0, atol=1e-6)
        assert f((raw * 4095).astype(np.uint16)).dtype == np.float64
        with pytest.raises(ValueError, match=">= 2"):
            f(np.zeros((1, 4)))
        with pytest.raises(ValueError, match="2-D"):
            f(np.zeros((4, 4, 3)))
