"""The front of hemicube twin: the `hemicube` command (hemicube.cli), whose sub-commands each package
registers (twin.cli, calibration.cli, reconstruction.cli; the designer's is hemicube.design), and the main job
that spans them, `hemicube validate` (hemicube.validate). Nothing below imports this package."""
