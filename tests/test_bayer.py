"""twin.camera.bayer: PFNC BayerRG12 / BayerRG12p byte layouts (against hand-worked bytes), CFA layouts and
bilinear demosaicing."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from twin.camera.bayer import (cfa_index, demosaic, from_bayer_rg12, mosaic, pack_bayer_rg12p, pfnc_name,
                        to_bayer_rg12, unpack_bayer_rg12p)


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
def test_demosaic_exact_for_constant_and_ramps(pattern):
    H, W = 9, 12
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    # a constant colour: exact everywhere, borders included
    const = np.broadcast_to(np.array([0.3, 1.7, 5.0]), (H, W, 3))
    np.testing.assert_allclose(demosaic(mosaic(const, pattern), pattern), const, rtol=0, atol=1e-12)
    # linear ramps, different per channel: exact away from the one-pixel border
    ramp = np.stack([1.0 + 0.5 * x + 0.25 * y, 3.0 - 0.75 * x + 2.0 * y, -2.0 + 0.125 * x - 1.5 * y], axis=-1)
    out = demosaic(mosaic(ramp, pattern), pattern)
    np.testing.assert_allclose(out[1:-1, 1:-1], ramp[1:-1, 1:-1], rtol=0, atol=1e-12)
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
