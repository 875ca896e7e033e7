"""The simulator backend (twin.capture.backends has the interface): `SimBackend` renders with the twin. Its
scene radiance depends linearly on the LED drive (Eq. 2), so it renders each camera's lumitexel projection
once for every pattern of the plan (`prepare`) and `show` only selects one; a pattern it was not prepared
for is rendered on demand.
"""
from __future__ import annotations

import numpy as np


class SimBackend:
    name = "sim"

    def __init__(self, rig, maps, *, seed: int, device: str = "cpu"):
        self.rig, self.maps, self.seed, self.device = rig, maps, int(seed), device
        self._surfaces: dict = {}
        self._radiance: dict = {}
        self._levels: np.ndarray | None = None

    def surfaces(self, camera: str):
        from twin.camera.imaging import trace_pixels

        if camera not in self._surfaces:
            self._surfaces[camera] = trace_pixels(self.rig, camera, self.maps)
        return self._surfaces[camera]

    def prepare(self, camera: str, patterns) -> None:
        """Render `patterns` (a PatternSet) for `camera` in one pass (one lumitexel evaluation per ray)."""
        from twin.camera.imaging import render

        todo = [k for k, lv in enumerate(patterns.levels) if (camera, lv.tobytes()) not in self._radiance]
        if not todo:
            return
        imgs = render(self.rig, camera, self.surfaces(camera), patterns.weights[todo], device=self.device)
        for k, img in zip(todo, imgs):
            self._radiance[(camera, patterns.levels[k].tobytes())] = img

    def show(self, levels: np.ndarray) -> dict:
        levels = np.asarray(levels)
        if levels.shape != (self.rig.num_leds, 3) or levels.dtype != np.uint8:
            raise ValueError(f"LED levels must be uint8 ({self.rig.num_leds}, 3), got {levels.dtype} {levels.shape}")
        self._levels = levels
        return {}

    def _current(self, camera: str) -> np.ndarray:
        if self._levels is None:
            raise RuntimeError("no pattern shown yet: call show() first")
        key = (camera, self._levels.tobytes())
        if key not in self._radiance:
            from twin.capture.patterns import PatternSet

            self.prepare(camera, PatternSet(self._levels[None], ("adhoc",), self.rig.name))
        return self._radiance[key]

    def meter(self, camera: str) -> float:
        return float(self._current(camera).max())

    def grab(self, camera: str, exposure_s: float, frame: int) -> np.ndarray:
        from twin.camera.sensor import simulate_raw

        cam = self.rig.camera(camera)
        return simulate_raw(self._current(camera), sensor=cam.sensor, exposure_s=exposure_s, seed=self.seed,
                            frame=frame, camera_key=f"{self.rig.digest()}/{camera}", device=self.device)

    def grab_bracket(self, camera: str, exposures_s, frames):
        return [self.grab(camera, t, f) for t, f in zip(exposures_s, frames)], list(exposures_s), {}

