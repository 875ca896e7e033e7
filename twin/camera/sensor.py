"""The camera sensor of the virtual capture: scene radiance at each pixel -> 12-bit raw digital numbers.

`simulate_raw` runs one Warp thread per pixel (CPU here, CUDA on a GPU, the same kernel). For pixel
(row i, col j) of a camera with parameters `twin.rig.camera.SensorParams`:

1. colour filter: channel c = CFA(sensor.bayer)[i % 2, j % 2] (`twin.camera.bayer`; RG: R at (0,0), G at
   (0,1) and (1,0), B at (1,1));
2. mean photo-electrons   mu = L[c] * electrons_per_radiance_s * t * (1 + PRNU_ij) + dark_current * t;
3. shot noise             n ~ Poisson(mu) (Warp's `wp.poisson`) for mu < GAUSS_LAMBDA, else
                          round(N(mu, mu)) (see below);
4. readout                e = n + DSNU_ij + N(0, read_noise_e);
5. full well              e = min(e, full_well_e);
6. ADC                    DN = clip(round(e / g + black_level_dn), 0, 2^bit_depth - 1),
                          g = gain_e_per_dn * 10^(-gain_db / 20) electrons per DN.

Randomness uses Warp's counter-based generator only: every draw of a pixel comes from
`wp.rand_init(seed32, pixel_id)` with pixel_id = i * 32768 + j (the pixel's position on the sensor,
independent of the image size and of thread scheduling) and a 32-bit seed made on the host:

* the per-capture noise (shot, read) from sha256(f"noise|{seed}|{frame}|{camera_key}");
* the FIXED patterns PRNU_ij ~ N(0, prnu) (relative gain) and DSNU_ij ~ N(0, dsnu_e) (electrons) from
  sha256(f"fpn|{camera_key}") only: the same for every seed and frame of a camera, different per camera
  (`fixed_pattern` returns them).

Hashes are sha256 (first 8 bytes, folded to 32 bits because Warp seeds are 32-bit), never Python's
`hash()`, so a given (seed, frame, camera_key, inputs) gives byte-identical output on every CPU run.
CUDA runs the same kernel and formulas; differences come only from float rounding of `log`/`exp`/
`sqrt`/`cos` in the last bit (this module is compiled without fast math). Measured on an H100 against
this CPU kernel (512 x 768 frames, Warp 1.19): the fixed patterns agree to 1-2 ulp (1.2e-7 relative);
raw frames are identical except for 0.07% of pixels (uniform 0-3x saturation), 0.04% (deep-well sensor,
1e6 e) and 0.0005% (0-20 e). In those pixels an ulp difference flipped an accept/reject decision of the
Poisson sampler, so they hold a different but identically distributed draw (up to ~3 sigma apart, e.g.
141 DN at 9000 e). CPU runs on two different x86-64 machines were byte-identical.

Shot noise at large lambda: `wp.poisson` uses the PTRS transformed-rejection sampler for lambda >= 10
(constant expected time) in float32. Measured on 2e6 draws per lambda: mean and variance correct to
<0.1% for lambda <= 1e4, but its float32 log-probabilities degrade above: variance +0.7% at 1e5, +3% at
1e6, -10% at 3e7 (and a uint32 result overflows beyond 4.3e9). Above GAUSS_LAMBDA = 1e4 electrons we
therefore draw round(mu + sqrt(mu) * N(0, 1)), whose skewness error (1/sqrt(mu) <= 0.01) is negligible;
mu is capped at 1e12 so that no input overflows (anything that large saturates anyway).

Vignetting and channel crosstalk act before the sensor and are applied by the caller in numpy
(`apply_vignetting`, `apply_crosstalk`, or both from a `Camera` with `apply_optics`).
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
import warp as wp

from twin.camera.bayer import cfa_index, cfa_table
from twin.rig.camera import SensorParams

wp.set_module_options({"fast_math": False})

GAUSS_LAMBDA = 1.0e4  # electrons: Poisson below, rounded Gaussian at and above
MU_MAX = 1.0e12  # electrons: cap on the mean before sampling
ROW_STRIDE = wp.constant(32768)  # pixel_id = row * ROW_STRIDE + col
MAX_WIDTH = ROW_STRIDE
MAX_HEIGHT = (2**31 - 1) // ROW_STRIDE  # 65535 rows: pixel_id stays a positive int32


def _init():
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()


# --- seeds ----------------------------------------------------------------------------------------
def _seed32(text: str) -> int:
    """A stable signed 32-bit Warp seed: the first 8 bytes of sha256(text), folded (xor) to 32 bits."""
    v = int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")
    v = (v ^ (v >> 32)) & 0xFFFFFFFF
    return v - (1 << 32) if v >= (1 << 31) else v


def fixed_pattern_seed(camera_key: str) -> int:
    return _seed32(f"fpn|{camera_key}")


def noise_seed(seed: int, frame: int, camera_key: str) -> int:
    return _seed32(f"noise|{int(seed)}|{int(frame)}|{camera_key}")


# --- the kernel -----------------------------------------------------------------------------------
@wp.struct
class SensorConsts:
    cfa: wp.vec4i  # channel at (row % 2) * 2 + (col % 2)
    e_per_rad: float  # electrons_per_radiance_s * exposure_s
    dark_e: float  # dark_current_e_per_s * exposure_s
    read_e: float
    full_well: float
    dn_per_e: float  # 1 / g
    black: float
    dn_max: float
    prnu: float
    dsnu: float
    gauss_lambda: float
    mu_max: float
    noise_seed: int
    fpn_seed: int


@wp.func
def fixed_pattern_at(fpn_seed: int, pid: int, prnu: float, dsnu: float):
    """(relative gain 1 + PRNU clamped at 0, DSNU offset in electrons) of one pixel."""
    s = wp.rand_init(fpn_seed, pid)
    gain = wp.max(1.0 + prnu * wp.randn(s), 0.0)
    offset = dsnu * wp.randn(s)
    return wp.vec2(gain, offset)


@wp.kernel
def raw_kernel(rad: wp.array3d(dtype=float), k: SensorConsts, out: wp.array2d(dtype=wp.uint16)):
    i, j = wp.tid()
    pid = i * ROW_STRIDE + j
    c = k.cfa[(i % 2) * 2 + (j % 2)]
    fp = fixed_pattern_at(k.fpn_seed, pid, k.prnu, k.dsnu)
    mu = rad[i, j, c] * k.e_per_rad * fp[0] + k.dark_e
    mu = wp.min(wp.max(mu, 0.0), k.mu_max)
    s = wp.rand_init(k.noise_seed, pid)
    n = float(0.0)
    if mu < k.gauss_lambda:
        n = float(wp.poisson(s, mu))
    else:
        n = wp.max(wp.floor(mu + wp.sqrt(mu) * wp.randn(s) + 0.5), 0.0)
    e = n + fp[1] + k.read_e * wp.randn(s)
    e = wp.min(e, k.full_well)
    dn = wp.floor(e * k.dn_per_e + k.black + 0.5)
    dn = wp.min(wp.max(dn, 0.0), k.dn_max)
    out[i, j] = wp.uint16(int(dn))


@wp.kernel
def fixed_pattern_kernel(fpn_seed: int, prnu: float, dsnu: float, gain: wp.array2d(dtype=float),
                         offset: wp.array2d(dtype=float)):
    i, j = wp.tid()
    fp = fixed_pattern_at(fpn_seed, i * ROW_STRIDE + j, prnu, dsnu)
    gain[i, j] = fp[0]
    offset[i, j] = fp[1]


# --- host side ------------------------------------------------------------------------------------
def effective_gain(sensor: SensorParams, gain_db: float = 0.0) -> float:
    """Electrons per DN at analogue gain `gain_db` (gain raises DN per electron)."""
    if not math.isfinite(gain_db):
        raise ValueError(f"gain_db must be finite, got {gain_db}")
    return sensor.gain_e_per_dn * 10.0 ** (-gain_db / 20.0)


def dn_max(sensor: SensorParams) -> int:
    return (1 << sensor.bit_depth) - 1


def saturation_electrons(sensor: SensorParams, gain_db: float = 0.0) -> float:
    """Collected electrons at which the output saturates: the full well or the ADC top, whichever first."""
    g = effective_gain(sensor, gain_db)
    return min(sensor.full_well_e, (dn_max(sensor) - sensor.black_level_dn) * g)


def saturation_radiance(sensor: SensorParams, exposure_s: float, gain_db: float = 0.0) -> float:
    """Radiance whose noise-free mean signal reaches saturation (full well or ADC max, whichever first)."""
    t = _check_exposure(exposure_s)
    e_sat = saturation_electrons(sensor, gain_db)
    return max(e_sat - sensor.dark_current_e_per_s * t, 0.0) / (sensor.electrons_per_radiance_s * t)


def expected_dn(radiance, sensor: SensorParams, exposure_s: float, gain_db: float = 0.0) -> np.ndarray:
    """Noise-free mean raw value (float64, (H, W)) with no fixed patterns: the mosaic of
    clip(clip(L k t + dark t, 0, full_well) / g + black, 0, DN max), unrounded. Near saturation the mean
    of the noisy, clipped output lies below this (clipping of the mean, not mean of the clipped)."""
    rad = _check_radiance(radiance)
    t = _check_exposure(exposure_s)
    g = effective_gain(sensor, gain_db)
    idx = cfa_index(sensor.bayer, rad.shape[0], rad.shape[1])
    L = np.take_along_axis(rad.astype(np.float64), idx[..., None], axis=2)[..., 0]
    e = np.clip(L * sensor.electrons_per_radiance_s * t + sensor.dark_current_e_per_s * t, 0.0, sensor.full_well_e)
    return np.clip(e / g + sensor.black_level_dn, 0.0, dn_max(sensor))


def fixed_pattern(sensor: SensorParams, camera_key: str, height: int, width: int, device="cpu"):
    """The camera's fixed patterns: (gain (H, W) float32 = 1 + PRNU, offset (H, W) float32 = DSNU in
    electrons), exactly those `simulate_raw` uses for `camera_key`."""
    _check_key(camera_key)
    _check_size(height, width)
    _init()
    gain = wp.empty((height, width), dtype=float, device=device)
    offset = wp.empty((height, width), dtype=float, device=device)
    wp.launch(fixed_pattern_kernel, dim=(height, width),
              inputs=[fixed_pattern_seed(camera_key), float(sensor.prnu), float(sensor.dsnu_e)],
              outputs=[gain, offset], device=device)
    return gain.numpy(), offset.numpy()


def simulate_raw(radiance, *, sensor: SensorParams, exposure_s: float, gain_db: float = 0.0, seed: int,
                 frame: int, camera_key: str, device="cpu") -> np.ndarray:
    """One raw frame: radiance (H, W, 3) float32 in the sensor's radiance unit (after vignetting and
    crosstalk) -> uint16 (H, W) digital numbers (see the module docstring for the model).

    Deterministic: the same (radiance, sensor, exposure_s, gain_db, seed, frame, camera_key) give
    byte-identical output on CPU."""
    rad = _check_radiance(radiance)
    t = _check_exposure(exposure_s)
    for name, v in (("seed", seed), ("frame", frame)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise TypeError(f"{name} must be an integer, got {v!r}")
    _check_key(camera_key)
    H, W = rad.shape[:2]
    _check_size(H, W)
    g = effective_gain(sensor, gain_db)
    k = SensorConsts()
    k.cfa = wp.vec4i(*[int(v) for v in cfa_table(sensor.bayer).ravel()])
    k.e_per_rad = float(sensor.electrons_per_radiance_s * t)
    k.dark_e = float(sensor.dark_current_e_per_s * t)
    k.read_e = float(sensor.read_noise_e)
    k.full_well = float(sensor.full_well_e)
    k.dn_per_e = float(1.0 / g)
    k.black = float(sensor.black_level_dn)
    k.dn_max = float(dn_max(sensor))
    k.prnu = float(sensor.prnu)
    k.dsnu = float(sensor.dsnu_e)
    k.gauss_lambda = float(GAUSS_LAMBDA)
    k.mu_max = float(MU_MAX)
    k.noise_seed = noise_seed(seed, frame, camera_key)
    k.fpn_seed = fixed_pattern_seed(camera_key)
    _init()
    rad_wp = wp.array(np.ascontiguousarray(rad, dtype=np.float32), dtype=float, device=device)
    out = wp.empty((H, W), dtype=wp.uint16, device=device)
    wp.launch(raw_kernel, dim=(H, W), inputs=[rad_wp, k], outputs=[out], device=device)
    return out.numpy()


# --- optics before the sensor (numpy) -------------------------------------------------------------
def vignetting_factor(K, width: int, height: int, coeffs) -> np.ndarray:
    """(H, W) radial factor 1 + a r^2 + b r^4 + c r^6, r = distance of the pixel centre from the principal
    point (K[0, 2], K[1, 2]) divided by the half-diagonal sqrt(W^2 + H^2) / 2 (pixel centres at integer
    coordinates, OpenCV convention)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got {K.shape}")
    a, b, c = (float(v) for v in coeffs)
    u = np.arange(width, dtype=np.float64) - K[0, 2]
    v = np.arange(height, dtype=np.float64) - K[1, 2]
    r2 = (u[None, :] ** 2 + v[:, None] ** 2) / (0.25 * (width * width + height * height))
    return 1.0 + r2 * (a + r2 * (b + r2 * c))


def apply_vignetting(rgb, K, width: int, height: int, coeffs, flat_field=None) -> np.ndarray:
    """rgb (H, W, 3) times the radial vignetting factor (`vignetting_factor`) and, when given, a per-pixel
    flat-field multiplier map (H, W). The result keeps a float input's dtype."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[:2] != (height, width):
        raise ValueError(f"rgb must be ({height}, {width}, 3), got {rgb.shape}")
    f = vignetting_factor(K, width, height, coeffs)
    if flat_field is not None:
        ff = np.asarray(flat_field, dtype=np.float64)
        if ff.shape != (height, width):
            raise ValueError(f"flat_field must be ({height}, {width}), got {ff.shape}")
        f = f * ff
    if not np.all(np.isfinite(f)) or f.min() < 0:
        raise ValueError("vignetting / flat-field factor must be finite and >= 0 everywhere")
    dtype = rgb.dtype if np.issubdtype(rgb.dtype, np.floating) else np.float64
    return (rgb * f[..., None]).astype(dtype, copy=False)


def apply_crosstalk(rgb, matrix) -> np.ndarray:
    """camera_rgb = M @ led_rgb at every pixel (M: 3x3, rows = camera channels)."""
    rgb = np.asarray(rgb)
    M = np.asarray(matrix, dtype=np.float64)
    if M.shape != (3, 3):
        raise ValueError(f"crosstalk matrix must be 3x3, got {M.shape}")
    if rgb.shape[-1:] != (3,):
        raise ValueError(f"rgb must end in 3 channels, got shape {rgb.shape}")
    dtype = rgb.dtype if np.issubdtype(rgb.dtype, np.floating) else np.float64
    return (rgb @ M.T).astype(dtype, copy=False)


def apply_optics(rgb, camera, flat_field=None) -> np.ndarray:
    """Crosstalk then vignetting with a `twin.rig.camera.Camera`'s own sensor parameters: the radiance that
    `simulate_raw` expects for that camera."""
    s = camera.sensor
    return apply_vignetting(apply_crosstalk(rgb, s.crosstalk), camera.K, camera.width, camera.height,
                            s.vignetting, flat_field)


# --- checks ---------------------------------------------------------------------------------------
def _check_radiance(radiance) -> np.ndarray:
    rad = np.asarray(radiance)
    if rad.ndim != 3 or rad.shape[2] != 3 or rad.shape[0] < 1 or rad.shape[1] < 1:
        raise ValueError(f"radiance must be (H, W, 3), got shape {rad.shape}")
    if not np.issubdtype(rad.dtype, np.number):
        raise TypeError(f"radiance must be numeric, got {rad.dtype}")
    if not np.all(np.isfinite(rad)):
        raise ValueError("radiance must be finite")
    if rad.min() < 0:
        raise ValueError(f"radiance must be >= 0, got min {rad.min()}")
    return rad


def _check_exposure(exposure_s) -> float:
    t = float(exposure_s)
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"exposure_s must be a positive finite number, got {exposure_s}")
    return t


def _check_key(camera_key) -> None:
    if not isinstance(camera_key, str) or not camera_key:
        raise TypeError(f"camera_key must be a non-empty string, got {camera_key!r}")


def _check_size(height: int, width: int) -> None:
    if not (1 <= width <= MAX_WIDTH and 1 <= height <= MAX_HEIGHT):
        raise ValueError(f"image {height}x{width} outside the supported 1..{MAX_HEIGHT} x 1..{MAX_WIDTH}")
