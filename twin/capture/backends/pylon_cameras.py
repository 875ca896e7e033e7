"""The rig's cameras through pypylon: Basler a2A5328-15ucPRO, or pylon's camera emulation (PYLON_CAMEMU) fed
with the raw frames the twin renders.

Configuration (`PROFILES`; the feature names differ between the real camera and the emulator):

    role               a2A5328-15ucPRO (ace 2 Pro, USB3)           pylon camera emulation
    pixel format       BayerRG12p (12-bit packed)                  BayerRG12 (the emulator has no packed formats)
    2664 x 2304        BinningSelector=Region1, 2 x 2, Average     BinningHorizontal/Vertical = 1; Width/Height
                       (full 5328 x 4608 field of view)             set to the rig's image
    exposure           ExposureTime (us); applied: the read-only   ExposureTime (us, whole microseconds)
                       BslEffectiveExposureTime
    trigger            FrameStart, On, Software                    the same
    frame id           GrabResult.BlockID                          the same (from 0 at each StartGrabbing)
    image source       the sensor                                  TestImageSelector=Off, ImageFileMode=On,
                                                                   ImageFilename = a folder of 16-bit PNGs
                                                                   (value << 4: BayerRG12 reads them MSB-aligned)

Why binning and not a region of interest: the released intrinsics (fx 4923 px at 2664 x 2304) cover the whole
5328 x 4608 sensor's field of view at half resolution; a 2664 x 2304 ROI would halve the field of view and
not match them. Colour binning on the ace 2 combines pixels of the same colour, so 2 x 2 binning keeps a
BayerRG mosaic; Average keeps the 12-bit scale and the sensor's response.

A photo's exposure bracket is grabbed as one grab session (`grab_bracket`): software trigger, then exactly one
frame, per exposure. The bracket is kept only when every frame arrived whole, each frame answers one of our
triggers (no frame was queued before a trigger, BlockIDs follow one another, none is left over after the last),
and the caller's `check` (the LED controller still showing the pattern) passes; otherwise it is discarded,
the reason counted, and the bracket taken again. A removed camera is reopened and reconfigured.
"""
from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin.capture.plan import EXPOSURE_LIMITS_S, DeviceError

CAMERA_MODEL = "a2A5328-15ucPRO"
SENSOR_SIZE = (5328, 4608)
EMULATED_SERIALS = "0815-{:04d}"  # pylon's emulated devices, in enumeration order


@dataclass(frozen=True)
class Profile:
    pixel_format: str
    binning: int
    binning_selector: str | None
    binning_mode: str | None
    applied_exposure: str   # the feature that says what exposure the sensor got
    settle_ms: int          # how long to watch for a frame beyond the bracket's last (a stray trigger's):
                            # a readout of the full sensor, for a real camera; an emulated stray is already there


PROFILES = {
    "basler": Profile("BayerRG12p", 2, "Region1", "Average", "BslEffectiveExposureTime", 100),
    "emulated": Profile("BayerRG12", 1, None, None, "ExposureTime", 0),
}


def genicam_cache() -> Path:
    """Where pylon caches GenICam XML: the project's .cache/ in a checkout, else the user's cache."""
    root = Path(__file__).resolve().parents[3]
    base = root / ".cache" if (root / "pyproject.toml").is_file() else Path.home() / ".cache" / "hemicube"
    return base / "genicam"


def import_pylon(emulated: int | None = None):
    """pypylon's (pylon, genicam) modules; with `emulated`, that many emulated cameras are enumerated."""
    cache = Path(os.environ.setdefault("GENICAM_CACHE_V3_5", str(genicam_cache())))
    cache.mkdir(parents=True, exist_ok=True)  # pylon ignores the variable when the folder does not exist
    if emulated:
        os.environ["PYLON_CAMEMU"] = str(emulated)  # read when devices are enumerated
    try:
        from pypylon import genicam, pylon
    except ImportError:
        raise DeviceError("the cameras need pypylon: pip install 'hemicube-twin[hardware]'") from None
    return pylon, genicam


def decode_frame(buffer, pixel_format: str, height: int, width: int) -> np.ndarray:
    """A grab buffer -> (H, W) uint16 BayerRG12 values."""
    from twin.camera.bayer import from_bayer_rg12, unpack_bayer_rg12p

    if pixel_format == "BayerRG12p":
        return unpack_bayer_rg12p(buffer, height, width)
    if pixel_format == "BayerRG12":
        return from_bayer_rg12(buffer, height, width)
    raise DeviceError(f"unexpected pixel format {pixel_format}")


def write_feed(folder: Path, raws) -> None:
    """The emulator's image folder for one bracket: 16-bit PNGs in name order, values << 4 (MSB-aligned)."""
    import cv2

    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for j, raw in enumerate(raws):
        if not cv2.imwrite(str(folder / f"e{j:02d}.png"), (raw.astype(np.uint16) << 4)):
            raise DeviceError(f"could not write the emulated camera's image {folder / f'e{j:02d}.png'}")


class _Retake(Exception):
    """This bracket cannot be kept; the message says why."""


@dataclass
class CameraStats:
    brackets: int = 0
    retakes: dict = field(default_factory=dict)  # reason -> count
    reconnects: int = 0
    injected: dict = field(default_factory=dict)


class PylonCamera:
    """One rig camera. `kind` is "basler" (a real a2A5328-15ucPRO, by serial number) or "emulated"."""

    def __init__(self, name: str, serial: str, kind: str, width: int, height: int, *, feed_dir: Path | None = None,
                 faults=None, timeout_s: float = 5.0, retries: int = 8):
        self.name, self.serial, self.kind = name, serial, kind
        self.profile = PROFILES[kind]
        self.width, self.height = width, height
        self.feed_dir, self.faults = feed_dir, faults
        self.timeout_ms, self.retries = int(timeout_s * 1000), retries
        self.pylon, self.genicam = import_pylon()
        self.stats = CameraStats()
        self.session = 0  # grab sessions so far: with BlockID, a frame's id
        self.cam = None
        self._open()

    # --- device ---------------------------------------------------------------------------------------
    def _open(self) -> None:
        tlf = self.pylon.TlFactory.GetInstance()
        devs = [d for d in tlf.EnumerateDevices() if d.GetSerialNumber() == self.serial]
        if not devs:
            raise DeviceError(f"camera {self.name}: no device with serial number {self.serial} (found: "
                              f"{[d.GetSerialNumber() for d in tlf.EnumerateDevices()] or 'none'})")
        try:
            self.cam = self.pylon.InstantCamera(tlf.CreateDevice(devs[0]))
            self.cam.Open()
            self._configure()
        except self.genicam.GenericException as e:
            raise DeviceError(f"camera {self.name} ({self.serial}): cannot configure it ({e})") from None

    def _set(self, feature: str, value) -> None:
        node = self.cam.GetNodeMap().GetNode(feature)
        if node is None:
            raise DeviceError(f"camera {self.name} ({self.serial}) has no feature {feature}")
        node.SetValue(value)

    def _get(self, feature: str):
        return self.cam.GetNodeMap().GetNode(feature).GetValue()

    def _configure(self) -> None:
        p = self.profile
        for feature, value in (("ExposureAuto", "Off"), ("GainAuto", "Off"), ("Gain", 0.0)):
            self._set(feature, value)
        if p.binning_selector:
            self._set("BinningSelector", p.binning_selector)
        if p.binning_mode:
            self._set("BinningHorizontalMode", p.binning_mode)
            self._set("BinningVerticalMode", p.binning_mode)
        self._set("BinningHorizontal", p.binning)
        self._set("BinningVertical", p.binning)
        self._set("PixelFormat", p.pixel_format)
        self._set("OffsetX", 0)
        self._set("OffsetY", 0)
        if self.kind == "basler" and (self._get("WidthMax"), self._get("HeightMax")) != (self.width, self.height):
            raise DeviceError(f"camera {self.name}: binned sensor is {self._get('WidthMax')} x "
                              f"{self._get('HeightMax')}, the rig's image {self.width} x {self.height}")
        self._set("Width", self.width)
        self._set("Height", self.height)
        for feature, value in (("TriggerSelector", "FrameStart"), ("TriggerMode", "On"),
                               ("TriggerSource", "Software")):
            self._set(feature, value)
        if self.kind == "emulated":
            self._set("TestImageSelector", "Off")
            self._set("ImageFileMode", "On")

    def _reconnect(self) -> None:
        """The camera went away (unplugged, power): let pylon forget it, find it again, set it up again."""
        self.stats.reconnects += 1
        try:
            self.cam.DestroyDevice()
        except self.genicam.GenericException:
            pass
        for attempt in range(self.retries):
            try:
                self._open()
                return
            except DeviceError:
                time.sleep(min(0.1 * 2 ** attempt, 2.0))
        raise DeviceError(f"camera {self.name} ({self.serial}) is gone and did not come back")

    def close(self) -> None:
        if self.cam is not None:
            if self.cam.IsGrabbing():
                self.cam.StopGrabbing()
            self.cam.Close()
            self.cam = None

    # --- grabbing -------------------------------------------------------------------------------------
    def _exposure(self, exposure_s: float) -> float:
        """Set the exposure; returns the one applied, in seconds."""
        self._set("ExposureTime", round(exposure_s * 1e6, 6))  # 1235 us, not 1234.9999999999998
        return float(self._get(self.profile.applied_exposure)) / 1e6  # the double nearest to it, as the plan's

    def _inject(self) -> None:
        kind = self.faults.pick() if self.faults is not None else None
        if kind is None:
            return
        self.stats.injected[kind] = self.stats.injected.get(kind, 0) + 1
        if kind == "failed":
            self._set("ForceFailedBufferCount", 1)
            self.cam.ForceFailedBuffer.Execute()
        elif kind == "disconnect":
            self.cam.FirePnPCallback.Execute()
        else:  # a stray trigger, waited for so that its frame is there before ours, as an early one would be
            self.cam.WaitForFrameTriggerReady(self.timeout_ms, self.pylon.TimeoutHandling_Return)
            self.cam.ExecuteSoftwareTrigger()
            self.cam.GetGrabResultWaitObject().Wait(self.timeout_ms)

    def _frame(self, expected_id: int | None):
        """Trigger and take the one frame that answers it: (raw, BlockID)."""
        pylon = self.pylon
        if self.cam.GetGrabResultWaitObject().Wait(0):
            raise _Retake("a frame arrived before our trigger")
        self._inject()
        if not self.cam.WaitForFrameTriggerReady(self.timeout_ms, pylon.TimeoutHandling_Return):
            raise _Retake("not ready for a trigger")
        if self.cam.GetGrabResultWaitObject().Wait(0):
            raise _Retake("a frame arrived before our trigger")
        self.cam.ExecuteSoftwareTrigger()
        res = self.cam.RetrieveResult(self.timeout_ms, pylon.TimeoutHandling_Return)
        if res is None or not res.IsValid():
            raise _Retake("no frame within the timeout")
        try:
            if not res.GrabSucceeded():
                raise _Retake("failed buffer")
            if expected_id is not None and res.BlockID != expected_id:
                raise _Retake("frame id out of sequence")
            if (res.Width, res.Height) != (self.width, self.height):
                raise _Retake("frame of the wrong size")
            raw = decode_frame(res.GetBuffer(), self.profile.pixel_format, self.height, self.width)
            return raw, int(res.BlockID)
        finally:
            res.Release()

    def grab_bracket(self, exposures_s, render=None, check=None):
        """One frame per exposure, kept only as a whole (see the module docstring). `render(applied)` gives the
        raw frames an emulated camera shows at the applied exposures; `check()` returns why the frames must not
        be kept, or None. Returns (raws, applied exposures in s, frame ids as [session, BlockID], the reasons
        of the brackets discarded on the way)."""
        reasons = []
        for _ in range(self.retries + 1):
            try:  # no backoff: a retake costs a bracket; a removed camera waits in _reconnect
                applied = [self._exposure(t) for t in exposures_s]
                if render is not None:
                    write_feed(self.feed_dir, render(applied))
                    self._set("ImageFilename", str(self.feed_dir))  # read when grabbing starts
                self.cam.StartGrabbing(self.pylon.GrabStrategy_OneByOne)
                self.session += 1
                raws, ids = [], []
                for t in exposures_s:
                    self._exposure(t)
                    raw, block = self._frame(ids[-1] + 1 if ids else None)
                    raws.append(raw)
                    ids.append(block)
                if self.cam.GetGrabResultWaitObject().Wait(self.profile.settle_ms):  # a frame beyond our triggers
                    raise _Retake("an extra frame (a trigger that was not ours)")
                reason = check() if check is not None else None
                if reason:
                    raise _Retake(reason)
                self.stats.brackets += 1
                return raws, applied, [[self.session, b] for b in ids], reasons
            except _Retake as e:
                reasons.append(str(e))
            except self.genicam.GenericException as e:
                if not self.cam.IsCameraDeviceRemoved():
                    reasons.append(f"camera error ({str(e).split(' : ')[0]})")
                else:
                    reasons.append("camera removed")
                    self._reconnect()
            finally:
                if self.cam is not None and self.cam.IsGrabbing():
                    self.cam.StopGrabbing()
            self.stats.retakes[reasons[-1]] = self.stats.retakes.get(reasons[-1], 0) + 1
        raise DeviceError(f"camera {self.name}: no complete bracket after {self.retries + 1} attempts "
                          f"({'; '.join(reasons)})")

    def meter(self, sensor, start_s: float = 1e-3, render=None) -> float:
        """The brightest radiance in view, from preview frames (never kept): shorten the exposure while
        photosites saturate, lengthen it while the image is in the noise. `render` as for grab_bracket."""
        from twin.camera.hdr import frame_radiance, saturation_threshold_dn

        limits = EXPOSURE_LIMITS_S
        thr = saturation_threshold_dn(sensor)
        t = start_s
        for _ in range(12):
            (raw,), (applied,), _, _ = self.grab_bracket([t], render)
            top = int(raw.max())
            if top >= thr and t > limits[0]:
                t = max(t / 8, limits[0])
            elif top < sensor.black_level_dn + 0.05 * (thr - sensor.black_level_dn) and t < limits[1]:
                t = min(t * 8, limits[1])
            else:
                break
        return float(max(frame_radiance(raw[raw < thr], applied, sensor).max(initial=0.0), 1e-12))


def camera_serials(names, kind: str, serials=None) -> list[str]:
    """Serial numbers of the rig's cameras, in the rig's order: the emulator's devices, the ones given, or
    the connected a2A5328-15ucPRO whose DeviceUserID is the rig camera's name."""
    if kind == "emulated":
        return [EMULATED_SERIALS.format(i) for i in range(len(names))]
    if serials:
        if len(serials) != len(names):
            raise DeviceError(f"--camera-serials needs {len(names)} serial numbers (cameras {', '.join(names)})")
        return list(serials)
    pylon, _ = import_pylon()
    found = {d.GetUserDefinedName(): d.GetSerialNumber() for d in pylon.TlFactory.GetInstance().EnumerateDevices()
             if d.GetModelName() == CAMERA_MODEL}
    missing = [n for n in names if n not in found]
    if missing:
        raise DeviceError(f"no {CAMERA_MODEL} whose DeviceUserID is {missing} (found {found or 'none'}); "
                          "set the user IDs or pass --camera-serials")
    return [found[n] for n in names]
