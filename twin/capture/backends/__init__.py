"""Device backends: the capture loop drives LEDs and cameras through this interface, so the same code runs
the simulator and the real hardware (a serial LED controller and Basler cameras).

    with open_backends(name, rig, maps, seed=..., device=..., **options) as backends:
        backend = backends["sample"]             (backends["empty"]: the empty board's photos)
        backend.surfaces(camera)                 what each pixel sees (ground truth), or None when unknown
        backend.prepare(camera, patterns)        get ready to show these patterns (a PatternSet)
        backend.show(levels) -> dict             drive the LEDs: (L, 3) uint8 levels; returns what the devices
                                                 acknowledged, for the manifest
        backend.meter(camera) -> float           the brightest radiance expected (for the exposure bracket)
        backend.grab_bracket(camera, exposures_s, frames, out) -> (applied exposures_s, dict for the manifest)
                                                 fill `out`, an (n, H, W) uint16 Warp array on the capture's
                                                 device, with one raw Bayer frame (BayerRG12 values) per
                                                 exposure; `frames` are the plan's frame ids (the twin's noise)

`sim` is the simulator (sim.py); `hardware` the LED controller and pypylon cameras (hardware.py, with
led_host/led_protocol and led_auth, the TCP links' token handshake; pylon_cameras; and the devices' emulators
led_emulator, with led_link, its TCP end, and faults). Add a backend as a module here and register how to open it
in BACKENDS.
"""
from contextlib import contextmanager

from twin.capture.backends.hardware import open_hardware
from twin.capture.backends.sim import SimBackend


@contextmanager
def _open_sim(rig, maps, *, seed: int, device: str = "cpu", truth=None):
    """`truth`: the rig the simulator renders with (the true device), when the capture records another (its
    calibration); it must have the same geometry (twin.capture.runner.capture checks)."""
    physics = truth if truth is not None else rig
    yield {"sample": SimBackend(physics, maps, seed=seed, device=device),
           "empty": SimBackend(physics, None, seed=seed, device=device)}


BACKENDS = {"sim": _open_sim, "hardware": open_hardware}


def open_backends(name: str, rig, maps, *, seed: int, device: str = "cpu", **options):
    """The 'sample' and 'empty' backends of `name`, open for the length of a `with` block."""
    return BACKENDS[name](rig, maps, seed=seed, device=device, **options)
