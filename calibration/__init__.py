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
docs/calibration.md describes each procedure and its goals."""
