"""The cameras through pypylon, against pylon's camera emulation (PYLON_CAMEMU) fed with frames the twin
renders: the configuration, exact frames, trigger/frame-id checks, failed buffers, disconnects and stray
triggers retried, and the packed BayerRG12p path checked against pylon's own image format converter."""
from __future__ import annotations

import numpy as np
import pytest

import twin
from twin.capture.backends.faults import CameraFaults
from twin.capture.backends.pylon_cameras import PylonCamera, camera_serials, import_pylon
from twin.capture.plan import CaptureError, DeviceError

H, W = 192, 222  # the mini rig's image
pylon, genicam = import_pylon(2)


def _camera(tmp_path, faults=None, retries=8):
    return PylonCamera("primary", "0815-0000", "emulated", W, H, feed_dir=tmp_path / "feed",
                       faults=CameraFaults(faults) if faults else None, retries=retries)


def _frames(n, seed):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 4096, (H, W), dtype=np.uint16) for _ in range(n)]


def test_packed_format_matches_pylons_converter():
    """The camera's BayerRG12p is unpacked by twin.camera.bayer; pylon's converter must read our packing as the
    same image it reads from the unpacked BayerRG12 buffer (a 1-LSB change is seen: no bit is lost)."""
    from twin.camera.bayer import pack_bayer_rg12p, to_bayer_rg12
    from twin.capture.backends.pylon_cameras import decode_frame

    raw = _frames(1, 0)[0]

    def converted(buf, pixel_type):
        img = pylon.PylonImage()
        img.AttachBytesObject(buf, pixel_type, W, H, 0)
        conv = pylon.ImageFormatConverter()
        conv.OutputPixelFormat = pylon.PixelType_Mono16
        return conv.Convert(img).Array.copy()

    packed = pack_bayer_rg12p(raw)
    assert np.array_equal(converted(packed, pylon.PixelType_BayerRG12p),
                          converted(to_bayer_rg12(raw), pylon.PixelType_BayerRG12))
    nudged = raw.copy()
    nudged[5, 7] ^= 1
    assert not np.array_equal(converted(pack_bayer_rg12p(nudged), pylon.PixelType_BayerRG12p),
                              converted(packed, pylon.PixelType_BayerRG12p))
    assert np.array_equal(decode_frame(packed, "BayerRG12p", H, W), raw)
    assert np.array_equal(decode_frame(to_bayer_rg12(raw), "BayerRG12", H, W), raw)


def test_emulated_camera_gives_the_frames_it_is_fed(tmp_path):
    cam = _camera(tmp_path)
    try:
        assert cam.cam.PixelFormat.Value == "BayerRG12" and cam.cam.TriggerMode.Value == "On"
        assert (cam.cam.Width.Value, cam.cam.Height.Value) == (W, H)
        for b in range(3):
            frames = _frames(3, b)
            raws, applied, ids, retakes = cam.grab_bracket([20e-6, 160e-6, 1280e-6], lambda a: frames)
            assert all(np.array_equal(x, y) for x, y in zip(raws, frames))
            assert applied == [20e-6, 160e-6, 1280e-6] and retakes == []
            assert ids == [[b + 1, 0], [b + 1, 1], [b + 1, 2]]
        # a bracket the caller's check refuses (the LEDs changed) is taken again, up to the limit
        reasons = iter(["the LEDs changed", None])
        raws, _, ids, retakes = cam.grab_bracket([1e-3], lambda a: frames[:1], lambda: next(reasons))
        assert retakes == ["the LEDs changed"] and ids == [[5, 0]]
        with pytest.raises(DeviceError, match=r"camera primary: no complete bracket after 9 attempts"):
            cam.grab_bracket([1e-3], lambda a: frames[:1], lambda: "never lit")
    finally:
        cam.close()


def test_failed_buffers_disconnects_and_stray_triggers_are_retaken(tmp_path):
    cam = _camera(tmp_path, "failed=0.1,disconnect=0.03,stray=0.1,seed=4", retries=20)
    try:
        for b in range(12):
            frames = _frames(3, 10 + b)
            raws, _, _, _ = cam.grab_bracket([1e-4, 8e-4, 6.4e-3], lambda a: frames)
            assert all(np.array_equal(x, y) for x, y in zip(raws, frames)), b  # never a wrong frame kept
        s = cam.stats
        assert set(s.injected) == {"failed", "disconnect", "stray"}
        assert s.reconnects == s.injected["disconnect"] > 0
        # each fault cost a retake (a removal can surface only at the next bracket, whose frames were then
        # taken again anyway)
        assert s.retakes["failed buffer"] == s.injected["failed"]
        assert s.retakes["a frame arrived before our trigger"] == s.injected["stray"]
    finally:
        cam.close()


def test_meter_from_preview_frames(tmp_path):
    """The real cameras' metering (preview frames, never kept), on the emulator fed with a rendered scene."""
    from twin.camera.sensor import simulate_raw

    sensor = twin.load_rig("mini").camera("primary").sensor
    radiance = np.full((H, W, 3), 2.0, np.float32)
    radiance[50:60, 70:90] = 40.0
    cam = _camera(tmp_path)
    try:
        seen = []

        def render(applied):
            seen.append(applied[0])
            return [simulate_raw(radiance, sensor=sensor, exposure_s=applied[0], seed=0, frame=len(seen),
                                 camera_key="meter")]
        estimate = cam.meter(sensor, start_s=1.0, render=render)
        assert len(seen) > 1 and seen[-1] < seen[0]  # it shortened the exposure until nothing saturated
        assert estimate == pytest.approx(40.0, rel=0.15)
    finally:
        cam.close()


def test_camera_errors(tmp_path):
    with pytest.raises(DeviceError, match="no device with serial number nope"):
        PylonCamera("primary", "nope", "emulated", W, H, feed_dir=tmp_path)
    assert camera_serials(["primary", "secondary"], "emulated") == ["0815-0000", "0815-0001"]
    with pytest.raises(DeviceError, match="needs 2 serial numbers"):
        camera_serials(["primary", "secondary"], "basler", ["123"])
    with pytest.raises(CaptureError, match="unknown 'jam'"):
        CameraFaults("jam=0.1")
