"""Calibration procedures: from photographs of calibration targets to the parameters a rig folder holds
(cameras, LED positions and profiles, vignetting, colour). A calibration writes a rig folder, which the
capture and the reconstruction read through `twin`; nothing here is imported by `reconstruction`, nor the
other way round (the import contract in pyproject.toml). The corrections that apply a rig's calibrated
values to photos are the camera's (twin.camera.correction).

    cameras.py     intrinsics, distortion and pose from ChArUco board photos
    vignetting.py  the flat field from photos of a flat-field source
    colour.py      each camera's crosstalk and colour matrix to XYZ from the white plate and a ColorChecker
    leds.py        the LEDs' positions, normals, profiles and intensities from a diffuse plate lit one LED at a time
                   (the bottom LEDs through the empty holder's acrylic)
    photos.py      what every procedure checks of a photo, and the binned rig the plate's photos use
    lab.py         the procedures in a lab's order against one true device in the twin (`hemicube calibrate`)
    cli.py         `hemicube calibrate`'s options and summary

Each procedure module has its calibration from photos and, beside it, its capture in the twin scored against the
twin's truth (`calibrate_cameras`, `calibrate_vignetting`, `calibrate_colour`, `calibrate_leds_from_plate`).
docs/calibration.md describes each procedure and its goals.

Exported here (`__all__`, each loaded on first use: `import calibration` imports neither Warp nor torch):
    calibrate_cameras, calibrate_vignetting, calibrate_colour, calibrate_leds_from_plate   the procedures
    stage, calibrate                                                                        the lab's run of them"""
from __future__ import annotations

from twin.lazy import lazy_exports as _lazy_exports

# each exported name and the module that defines it, loaded on first use
_LAZY = {"calibrate_cameras": "calibration.cameras", "calibrate_vignetting": "calibration.vignetting",
         "calibrate_colour": "calibration.colour", "calibrate_leds_from_plate": "calibration.leds",
         "stage": "calibration.lab", "calibrate": "calibration.lab"}
__all__ = list(_LAZY)
__getattr__, __dir__ = _lazy_exports(__name__, _LAZY)
