"""What happens in a camera: image formation (pixel rays through the lens model, hits on the holder frame,
sample and board, radiance through the forward model), the sensor to the bit, Bayer/PFNC formats and the
HDR merge. The cameras' calibrated parameters are part of the rig (twin.rig.camera)."""
