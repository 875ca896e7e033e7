"""The simulator backend (twin.capture.backends has the interface): `SimBackend` renders with the twin. Its
scene radiance depends linearly on the LED drive (Eq. 2), so it renders each camera's lumitexel projection
once for every pattern of the plan (`prepare`) and `show` only selects one; a pattern it was not prepared
for is rendered on demand. Surfaces, images and raw frames stay on the backend's device (twin.camera).
"""
from __future__ import annotations

import numpy as np


def check_levels(rig, levels) -> np.ndarray:
    """LED levels as every backend takes them: uint8 (L, 3)."""
    levels = np.asarray(levels)
    if levels.shape != (rig.num_leds, 3) or levels.dtype != np.uint8:
        raise ValueError(f"LED levels must be uint8 ({rig.num_leds}, 3), got {levels.dtype} {levels.shape}")
    return levels


class SimBackend:
    name = "sim"

    def __init__(self, rig, maps, *, seed: int, device: str = "cpu"):
        self.rig, self.maps, self.seed, self.device = rig, maps, int(seed), device
        self._surfaces: dict = {}
        self._radiance: dict = {}  # (camera, levels bytes) -> ((H, W) vec3f Warp view of a rendered image, max)
        self._levels: np.ndarray | None = None
        self._fixed: dict = {}  # camera -> its sensor's (gain, offset) fixed-pattern arrays on the device

    def surfaces(self, camera: str):
        from twin.camera.imaging import trace_pixels

        if camera not in self._surfaces:
            self._surfaces[camera] = trace_pixels(self.rig, camera, self.maps, device=self.device)
        return self._surfaces[camera]

    def prepare(self, camera: str, patterns) -> None:
        """Render `patterns` (a PatternSet) for `camera` in one pass (one lumitexel evaluation per ray)."""
        import warp as wp

        from twin.camera.imaging import render_device

        todo = [k for k, lv in enumerate(patterns.levels) if (camera, lv.tobytes()) not in self._radiance]
        if not todo:
            return
        imgs = render_device(self.rig, camera, self.surfaces(camera), patterns.weights[todo], device=self.device)
        # the brightest value of each image, for the exposure (one transfer for all of them)
        peak = wp.to_torch(imgs).reshape(len(todo), -1).amax(dim=1).cpu().numpy()
        for i, k in enumerate(todo):
            self._radiance[(camera, patterns.levels[k].tobytes())] = (imgs[i], float(peak[i]))

    def show(self, levels: np.ndarray) -> dict:
        self._levels = check_levels(self.rig, levels)
        return {}

    def _current(self, camera: str):
        if self._levels is None:
            raise RuntimeError("no pattern shown yet: call show() first")
        key = (camera, self._levels.tobytes())
        if key not in self._radiance:
            from twin.capture.patterns import PatternSet

            self.prepare(camera, PatternSet(self._levels[None], ("adhoc",), self.rig.name))
        return self._radiance[key]

    def meter(self, camera: str) -> float:
        return self._current(camera)[1]

    def grab(self, camera: str, exposure_s: float, frame: int, out) -> None:
        from twin.camera.sensor import fixed_pattern_arrays, raw_frame, sensor_consts

        cam = self.rig.camera(camera)
        radiance = self._current(camera)[0]
        consts = sensor_consts(cam.sensor, exposure_s=exposure_s, seed=self.seed, frame=frame,
                               camera_key=f"{self.rig.digest()}/{camera}")
        if camera not in self._fixed:  # the camera's fixed patterns, the same for every frame: drawn once
            self._fixed[camera] = fixed_pattern_arrays(consts, *radiance.shape[:2], radiance.device)
        raw_frame(radiance, consts, out, fixed=self._fixed[camera])

    def grab_bracket(self, camera: str, exposures_s, frames, out):
        for j, (t, f) in enumerate(zip(exposures_s, frames)):
            self.grab(camera, t, f, out[j])
        return list(exposures_s), {}
