"""The front of hemicube twin: the `hemicube` command (hemicube.cli), whose sub-commands each package
registers (twin.cli, reconstruction.cli), and the main job that spans them, `hemicube validate`
(hemicube.validate). Nothing below imports this package."""
