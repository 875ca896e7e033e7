"""Calibration procedures: from photographs of calibration targets to the parameters a rig folder holds
(cameras, LED positions and profiles, vignetting, colour). A calibration writes a rig folder, which the
capture and the reconstruction read through `twin`; nothing here is imported by `reconstruction`, nor the
other way round (the import contract in pyproject.toml). The corrections that apply a rig's calibrated
values to photos are the camera's (twin.camera.correction). Built: the cameras (`cameras.py`); the LEDs, vignetting and colour are not (issue #16, docs/calibration.md)."""
