"""The hardware backend: the serial LED controller (led_host) and the rig's cameras through pypylon
(pylon_cameras), behind the same interface as the simulator, so that `hemicube capture --backend hardware`
runs the same plan, session folder and resume.

    --cameras basler     the real a2A5328-15ucPRO cameras; exposures metered from preview frames
    --cameras emulated   pylon's camera emulation, fed with raw frames the twin renders from the pattern the
                         controller acknowledges as displayed when the bracket starts (STATE), so a wrong
                         pattern shown is a wrong frame, which the check below then refuses; metered by the
                         twin: the photos equal `--backend sim`'s, byte for byte

For each photo: `show` uploads and latches the pattern and keeps the controller's acknowledgement (its
displayed CRC goes into the manifest); `meter` and `grab_bracket` keep the metering and the exposure bracket
(one grab session) only if, afterwards, the controller still displays that pattern under the same boot id
(else it lights it again and meters or takes the bracket again); the camera frame ids and any retakes go
into the manifest.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from twin.capture.backends.led_protocol import crc32
from twin.capture.backends.sim import SimBackend, check_levels
from twin.capture.plan import CaptureError, DeviceError
from twin.capture.plausibility import METER_ATTEMPTS

CAMERA_KINDS = ("emulated", "basler")


class Devices:
    """What the 'sample' and the 'empty' backends share: one controller link and the cameras. `run` names
    this process's use of them: camera frame ids ([grab session, BlockID]) restart with every run, so the
    manifest keys them by run (a resumed capture has several)."""

    def __init__(self, led, cameras: dict, prompt=None):
        self.led, self.cameras, self.prompt = led, cameras, prompt
        self.run = f"{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"


class HardwareBackend:
    name = "hardware"

    def __init__(self, rig, devices: Devices, twin: SimBackend | None, *, empty_board: bool = False):
        self.rig, self.devices, self.twin = rig, devices, twin
        self._empty_board = empty_board  # this backend's photos need the sample taken off the board
        off = np.zeros((rig.num_leds, 3), np.uint8)  # what a controller shows after a reset
        self._known: dict[int, np.ndarray] = {crc32(off.tobytes()): off}  # CRC -> levels, every pattern sent
        self._levels = None
        self._ack = None
        self._retakes: list[str] = []  # why the meterings of the photo shown were discarded (see meter)

    def surfaces(self, camera: str):
        return self.twin.surfaces(camera) if self.twin is not None else None

    def prepare(self, camera: str, patterns) -> None:
        for levels in patterns.levels:  # store them on the controller while its slots last
            self._known[self.devices.led.load(levels)] = levels
        if self.twin is not None:
            self.twin.prepare(camera, patterns)

    def show(self, levels: np.ndarray) -> dict:
        levels = check_levels(self.rig, levels)
        if self._empty_board and self.devices.prompt is not None:
            self.devices.prompt("take the sample off the board for the empty-board photo, then press Enter")
            self.devices.prompt = None
        self._levels = levels
        self._known[crc32(levels.tobytes())] = levels
        self._retakes = []
        self._ack = self.devices.led.show(levels)
        return {"led_crc": f"{self._ack.displayed_crc:08x}"}

    def _displayed(self) -> np.ndarray:
        """The levels the controller acknowledges as displayed now: what emulated cameras see."""
        crc = self.devices.led.query().displayed_crc
        try:
            return self._known[crc]
        except KeyError:
            raise DeviceError(f"the LED controller displays a pattern this capture never sent (CRC {crc:08x}), "
                              "which the emulated cameras cannot render") from None

    def meter(self, camera: str) -> float:
        """The brightest radiance in view, metered under the pattern the controller acknowledged: kept only when,
        afterwards, the controller still displays it under the same boot id; else the pattern is lit again and
        metered again, at most METER_ATTEMPTS times. Why: a controller reset between the SHOW and the metering
        turns the LEDs off, so the photo would be metered in the dark and exposed for darkness, and its frames
        taken once the bracket's check has lit the pattern again."""
        for _ in range(METER_ATTEMPTS):
            if self.twin is None:
                value = self.devices.cameras[camera].meter(self.rig.camera(camera).sensor)
            else:
                self.twin.show(self._displayed())
                value = self.twin.meter(camera)
            reason = self._still_lit("metering")
            if reason is None:
                return value
            self._retakes.append(reason)
        why = Counter(self._retakes)
        raise DeviceError(f"camera {camera}: the LEDs did not stay lit through the metering in {METER_ATTEMPTS} "
                          f"attempts ({'; '.join(f'{n} x {r}' if n > 1 else r for r, n in why.items())})")

    def _still_lit(self, during: str) -> str | None:
        """None when the controller still shows what it acknowledged; else light the pattern again and say why
        what was just measured `during` (the metering, the bracket) cannot be kept."""
        state, ack = self.devices.led.query(), self._ack
        if (state.displayed_crc, state.boot_id) == (ack.displayed_crc, ack.boot_id):
            return None
        self._ack = self.devices.led.show(self._levels)
        reset = ", the controller reset" if state.boot_id != ack.boot_id else ""
        return f"the LEDs changed during the {during} (displayed {state.displayed_crc:08x}{reset})"

    def _render(self, camera: str, frames):
        """What the emulated camera is fed: the twin's raw frames of the acknowledged pattern."""
        import warp as wp

        def render(applied):
            self.twin.show(self._displayed())
            cam = self.rig.camera(camera)
            out = wp.empty((len(applied), cam.height, cam.width), dtype=wp.uint16, device=self.twin.device)
            for j, (t, f) in enumerate(zip(applied, frames)):
                self.twin.grab(camera, t, f, out[j])
            return list(out.numpy())
        return render

    def grab_bracket(self, camera: str, exposures_s, frames, out):
        import warp as wp

        render = self._render(camera, frames) if self.twin is not None else None
        raws, applied, ids, retakes = self.devices.cameras[camera].grab_bracket(
            exposures_s, render, lambda: self._still_lit("bracket"))
        wp.copy(out, wp.array(np.stack(raws), dtype=wp.uint16, device="cpu"))
        retakes = self._retakes + retakes
        return applied, {"camera_run": self.devices.run, "camera_frames": ids,
                         **({"retakes": retakes} if retakes else {})}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's
    return True


def _feed_folder() -> Path:
    """This process's folder of images for the emulated cameras; those of processes that are gone (killed
    captures) are removed."""
    root = Path(tempfile.gettempdir())
    for old in root.glob("hemicube-camemu-*"):
        pid = old.name.rpartition("-")[2]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    folder = root / f"hemicube-camemu-{os.getpid()}"
    shutil.rmtree(folder, ignore_errors=True)
    return folder


@contextmanager
def open_hardware(rig, maps, *, seed: int, device: str = "cpu", led: str | None = None, cameras: str | None = None,
                  camera_serials=None, camera_faults=None, led_baud: int | None = None, prompt=None):
    """{'sample': backend, 'empty': backend} over one controller link and one set of cameras. `camera_faults`:
    a spec, or a CameraFaults whose counts the caller reads afterwards."""
    from twin.capture.backends.faults import CameraFaults
    from twin.capture.backends.led_host import DEFAULT_BAUD, LedController
    from twin.capture.backends.pylon_cameras import PylonCamera, camera_serials as find_serials, import_pylon

    if not led:
        raise CaptureError("--backend hardware needs --led URL (the LED controller: /dev/ttyACM0, socket://HOST:PORT)")
    if cameras not in CAMERA_KINDS:
        raise CaptureError(f"--backend hardware needs --cameras {' or '.join(CAMERA_KINDS)}, got {cameras!r}")
    if camera_faults and cameras != "emulated":
        raise CaptureError("--camera-faults injects faults into emulated cameras only")
    emulated = cameras == "emulated"
    names = list(rig.cameras)
    faults = camera_faults if isinstance(camera_faults, CameraFaults) or not camera_faults else CameraFaults(camera_faults)
    import_pylon(len(names) if emulated else None)
    feed = _feed_folder() if emulated else None
    opened = []
    ctl = LedController(led, rig.num_leds, baudrate=led_baud or DEFAULT_BAUD)
    try:
        for name, serial in zip(names, find_serials(names, cameras, camera_serials)):
            cam = rig.camera(name)
            opened.append(PylonCamera(name, serial, cameras, cam.width, cam.height,
                                      feed_dir=feed / name if emulated else None, faults=faults))
        devices = Devices(ctl, dict(zip(names, opened)), prompt=None if emulated else prompt)
        twins = ({k: SimBackend(rig, m, seed=seed, device=device) for k, m in (("sample", maps), ("empty", None))}
                 if emulated else {"sample": None, "empty": None})
        yield {"sample": HardwareBackend(rig, devices, twins["sample"]),
               "empty": HardwareBackend(rig, devices, twins["empty"], empty_board=True)}
    finally:
        for cam in opened:
            cam.close()
        ctl.close()
        if feed is not None:
            shutil.rmtree(feed, ignore_errors=True)
