"""Pictures of the rig: the pyvista 3-D view and the unfolded-cube (cross) images of patterns."""
