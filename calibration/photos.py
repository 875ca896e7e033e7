"""What every calibration procedure asks of a photo before it reads it: the camera's size and finite values,
or an error of the procedure's own type naming the photo; and what the procedures that photograph the plate
under one LED at a time share (the LEDs', the colour's): a rig with its cameras binned, the LEDs rendered at once."""
from __future__ import annotations

import numpy as np


def checked_photo(photo, camera, label: str, error: type) -> np.ndarray:
    """`photo` as (H, W, 3) float64 for `camera`, or `error` naming `label`."""
    photo = np.asarray(photo, np.float64)
    if photo.shape != (camera.height, camera.width, 3):
        raise error(f"{label}: photo is {photo.shape}, camera {camera.name!r} gives ({camera.height}, "
                    f"{camera.width}, 3)")
    if not np.isfinite(photo).all():
        raise error(f"{label}: photo contains NaN or Inf")
    return photo


LED_BATCH = 64  # LEDs rendered at once (the radiance of a batch: 64 x H x W x 3 float64)


def binned_rig(rig, b: int):
    """The rig with its cameras binned b x b (Camera.resized; the flat-field maps averaged over the bins)."""
    from dataclasses import replace

    if b == 1:
        return rig

    def down(m, cam):
        H, W = (cam.height // b) * b, (cam.width // b) * b
        return np.asarray(m)[:H, :W].reshape(H // b, b, W // b, b).mean(axis=(1, 3)).astype(np.float32)

    cams = {n: c.resized(1.0 / b) for n, c in rig.cameras.items()}
    return replace(rig, cameras=cams, flat_fields={n: down(m, rig.cameras[n]) for n, m in rig.flat_fields.items()})
