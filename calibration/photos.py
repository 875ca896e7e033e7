"""What every calibration procedure asks of a photo before it reads it: the camera's size and finite values,
or an error of the procedure's own type naming the photo."""
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
