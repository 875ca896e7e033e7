"""Device backends: the capture loop drives LEDs and cameras through this interface, so the same code runs
the simulator and, later, the real hardware (a serial LED controller and Basler cameras).

    backend = BACKENDS[name](rig, maps, seed=..., device=...)
    backend.surfaces(camera)                     what each pixel sees (ground truth; the simulator only)
    backend.prepare(camera, patterns)            get ready to show these patterns (a PatternSet)
    backend.show(levels)                         drive the LEDs: (L, 3) uint8 levels
    backend.meter(camera) -> float               the brightest radiance expected (for the exposure bracket)
    backend.grab(camera, exposure_s, frame, out)  fill `out`, an (H, W) uint16 Warp array on the capture's
                                                 device, with a raw Bayer frame (BayerRG12 values)

Add a backend as a module here and register it in BACKENDS.
"""
from twin.capture.backends.sim import SimBackend

BACKENDS = {"sim": SimBackend}
