"""Colour from spectra (docs/calibration.md): the LEDs' emission spectra, the cameras' colour-filter sensitivities and a
surface's spectral reflectance, from which follow a camera's 3x3 crosstalk (`Camera.sensor.crosstalk`) and
what it records of a coloured target such as a ColorChecker.

The twin renders in LED RGB: three grey renders, one per LED channel, as the reference does (its §2.5). A
camera channel k then sees LED channel c through

    M[k, c] = ∫ e_c(λ) s_k(λ) dλ / ∫ e_c(λ) s_c(λ) dλ                                  (the crosstalk)

with e_c the channel's emission spectrum and s_k the colour filter's sensitivity. The denominator fixes the
unit of LED channel c as what the matching camera channel sees of it (M's diagonal is 1; the nominal rigs'
identity is the limit of perfectly separated filters). A surface of spectral reflectance ρ(λ) lit by channel c
gives camera channel k

    T[k, c](ρ) = ∫ ρ(λ) e_c(λ) s_k(λ) dλ / ∫ e_c(λ) s_c(λ) dλ,                           T(1) = M

which no 3x3 applied to per-channel albedos reproduces in general (a reflectance that varies within an LED's
band): the simulation of a coloured chart is richer than the colour matrix a calibration fits.

Colorimetry (CIE 1931 2° observer): the XYZ of a surface under the LEDs' white W(λ) = Σ_c w_c e_c(λ), scaled
so that a perfect white diffuser has Y = 1, is ∫ ρ W x̄ / ∫ W ȳ; CIE Lab takes W's own XYZ as its white.

Spectra: each LED channel is Ohno's (2005) single-LED model (`colour.sd_single_led`), peak and half-width of a
typical RGB package (630 / 525 / 465 nm; 20 / 35 / 25 nm). The cameras' sensitivities are a measured Bayer
camera's from colour-science (`Nikon 5100 (NPL)`): the Basler's Sony sensor's curves are not published as
data, and the crosstalk depends on a real CFA's overlaps, not on its exact brand. `device_spectra(seed)` draws
a device's own: each LED channel's peak N(0, 2 nm) (LED makers bin the dominant wavelength in 2.5-5 nm steps)
and half-width x U(0.9, 1.1); each camera channel's sensitivity shifted by N(0, 3 nm) (the dyes of one sensor
batch).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from twin.optics.spectra import WAVELENGTHS, resample, spectral_shape

__all__ = ["DeviceSpectra", "device_spectra", "with_crosstalk", "chart_radiance"]

NOMINAL_LEDS = ((630.0, 20.0), (525.0, 35.0), (465.0, 25.0))  # (peak, half spectral width) nm: R, G, B
CAMERA_SENSITIVITIES = "Nikon 5100 (NPL)"
CMFS = "CIE 1931 2 Degree Standard Observer"


@dataclass(frozen=True)
class DeviceSpectra:
    """One device's spectra: its LEDs' (all LEDs share the three channels' parts) and each camera's."""
    leds: tuple[tuple[float, float], ...] = NOMINAL_LEDS  # (peak, half width) nm per channel R, G, B
    camera_shift_nm: tuple[tuple[str, tuple[float, float, float]], ...] = ()  # per camera: each channel's shift
    sensitivities: str = CAMERA_SENSITIVITIES

    def __post_init__(self):
        if len(self.leds) != 3 or not all(np.isfinite(v) and v > 0 for pw in self.leds for v in pw):
            raise ValueError(f"DeviceSpectra.leds must be 3 (peak, half width) pairs in nm, got {self.leds!r}")

    def emission(self) -> np.ndarray:
        """(N, 3) e_c(λ) on WAVELENGTHS, each channel's peak 1."""
        import colour

        e = np.stack([resample(colour.sd_single_led(p, shape=spectral_shape(), half_spectral_width=w))
                      for p, w in self.leds], axis=1)
        return e / e.max(axis=0)

    def sensitivity(self, camera: str) -> np.ndarray:
        """(N, 3) s_k(λ) of `camera`'s colour filters on WAVELENGTHS, each channel shifted by its own shift."""
        import colour

        base = colour.MSDS_CAMERA_SENSITIVITIES[self.sensitivities]
        lam = np.asarray(base.wavelengths, np.float64)
        vals = np.asarray(base.values, np.float64)
        shift = dict(self.camera_shift_nm).get(camera, (0.0, 0.0, 0.0))
        return np.stack([np.interp(WAVELENGTHS - shift[k], lam, vals[:, k], left=0.0, right=0.0)
                         for k in range(3)], axis=1)

    def transfer(self, camera: str, reflectance) -> np.ndarray:
        """(..., 3, 3) T[k, c] of surfaces with spectral reflectance (..., N) on WAVELENGTHS (module docstring)."""
        e, s = self.emission(), self.sensitivity(camera)
        unit = np.einsum("nc,nc->c", e, s)  # what camera channel c sees of LED channel c
        rho = np.asarray(reflectance, np.float64)
        return np.einsum("...n,nc,nk->...kc", rho, e, s) / unit

    def crosstalk(self, camera: str) -> np.ndarray:
        """(3, 3) M = T(1): camera RGB = M @ LED RGB."""
        return self.transfer(camera, np.ones(len(WAVELENGTHS)))

    def white(self, weights) -> np.ndarray:
        """(N,) the LEDs' white W(λ) = Σ_c w_c e_c(λ) for LED-RGB weights w (3,)."""
        return self.emission() @ np.asarray(weights, np.float64)

    def xyz(self, reflectance, weights) -> np.ndarray:
        """(..., 3) CIE XYZ of surfaces (..., N) under the white of `weights`, a perfect white diffuser at Y = 1."""
        import colour

        cmf = resample(colour.MSDS_CMFS[CMFS])
        W = self.white(weights)
        return np.asarray(reflectance, np.float64) @ (W[:, None] * cmf) / (W @ cmf[:, 1])

    def to_dict(self) -> dict:
        return {"leds_peak_halfwidth_nm": [list(p) for p in self.leds], "camera_sensitivities": self.sensitivities,
                "camera_shift_nm": {n: list(s) for n, s in self.camera_shift_nm}}


def device_spectra(cameras, seed: int | None = None) -> DeviceSpectra:
    """The nominal spectra (seed None) or a device's own drawn from `seed` (module docstring), for the cameras
    named in `cameras`."""
    if seed is None:
        return DeviceSpectra(camera_shift_nm=tuple((str(n), (0.0, 0.0, 0.0)) for n in cameras))
    rng = np.random.default_rng([int(seed), 19])
    leds = tuple((float(p + rng.normal(0, 2.0)), float(w * rng.uniform(0.9, 1.1))) for p, w in NOMINAL_LEDS)
    shifts = tuple((str(n), tuple(float(v) for v in rng.normal(0, 3.0, 3))) for n in cameras)
    return DeviceSpectra(leds=leds, camera_shift_nm=shifts)


def with_crosstalk(rig, spectra: DeviceSpectra):
    """`rig` with each camera's crosstalk the one `spectra` gives it: the rig a device with these spectra is."""
    cams = {n: replace(c, sensor=replace(c.sensor, crosstalk=tuple(map(tuple, spectra.crosstalk(n).tolist()))))
            for n, c in rig.cameras.items()}
    return replace(rig, cameras=cams)


def chart_radiance(chart, rig, spectra: DeviceSpectra, camera_name: str, white) -> np.ndarray:
    """(H, W, 3) float64 CAMERA-RGB radiance of a colour chart (twin.targets.colorchecker) seen by `camera_name`:
    per pixel T(ρ of its patch) @ `white` (H, W, 3), the LED-RGB radiance a perfect white lying where the chart
    lies sends to that pixel under the chart's light (DiffusePlate(albedo=1).lit_radiance, or a plate's photo
    model divided by its albedo); the module docstring's T. Photograph it with
    twin.camera.hdr.still_photo(..., camera_rgb=True): the crosstalk is in T already."""
    from twin.targets.colorchecker import FRAME, OFF

    _, rho = chart.names_and_spectra()
    rho = np.concatenate([rho, np.full((1, len(WAVELENGTHS)), chart.frame_reflectance)])  # FRAME is the last row
    T = spectra.transfer(camera_name, rho)
    idx = chart.patch_map(rig, rig.camera(camera_name))
    idx = np.where(idx == FRAME, len(rho) - 1, idx)
    out = np.einsum("hwkc,hwc->hwk", T[np.maximum(idx, 0)], np.asarray(white, np.float64))
    out[idx == OFF] = 0.0
    return out
