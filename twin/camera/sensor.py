"""The camera sensor of the virtual capture: scene radiance at each pixel -> 12-bit raw digital numbers.

`simulate_raw` (numpy in and out) and `raw_frame` (Warp arrays, no host round trip) run one Warp thread per
pixel (CPU here, CUDA on a GPU, the same kernel). For pixel (row i, col j) of a camera with parameters
`twin.rig.camera.SensorParams`:

1. colour filter: channel c = CFA(sensor.bayer)[i % 2, j % 2] (`twin.camera.bayer`; RG: R at (0,0), G at
   (0,1) and (1,0), B at (1,1));
2. mean photo-electrons   mu = L[c] * electrons_per_radiance_s * t * (1 + PRNU_ij) + dark_current * t;
3. shot noise             n = F^-1(u1; mu), the Poisson quantile of a uniform draw u1 (see below);
4. readout                e = n + DSNU_ij + read_noise_e * Phi^-1(u2);
5. full well              e = min(e, full_well_e);
6. ADC                    DN = clip(floor(e / g + black_level_dn + 0.5), 0, 2^bit_depth - 1),
                          g = gain_e_per_dn * 10^(-gain_db / 20) electrons per DN.

Every draw is an inverse-CDF transform of a uniform, so a pixel's value is a monotone, piecewise-constant
function of its mean for fixed draws: a mean moved by a rounding error moves the shot-noise count by at
most one electron (and only when the draw lies within that error of a quantile step), i.e. the DN by at most
1. (A rejection sampler, used before, could flip an accept/reject decision on the last bit of the mean and
give an unrelated draw, up to ~3 sigma away.) The Poisson quantile:

* mu < POISSON_INVERSION_MAX (64): exact inversion, the smallest n with P(N <= n) >= u1, by summing the pmf
  from n = 0 in float64 (at most mu + 12 sqrt(mu) + 12 terms);
* above: the Cornish-Fisher expansion of the Poisson quantile with the lattice (Sheppard) correction,
      n = floor(mu + sqrt(mu) z + (z^2 + 2) / 6 - (z^3 + 2 z) / (72 sqrt(mu))),  z = Phi^-1(u1),
  whose skew term is exact to O(1/mu): measured against scipy.stats.poisson.ppf on 4e5 draws it returns the
  exact quantile except in 3e-4 of draws at mu = 64, 2e-5 at 1e3 and 3e-6 at 1e4 (and then one count
  away). tests/test_sensor.py checks mean, variance, skewness and a chi-square against scipy.stats.poisson.
  mu is capped at MU_MAX = 1e12 electrons (anything that large saturates anyway).

Phi^-1 is Wichura's AS 241 (PPND16, relative error ~1e-16) in float64, from a 52-bit uniform made of two
32-bit draws, so the tails reach |z| = 8.2; it uses only log, sqrt and rational functions.

Randomness uses Warp's counter-based generator only: every draw of a pixel comes from
`wp.rand_init(seed32, pixel_id)` with pixel_id = i * 32768 + j (the pixel's position on the sensor,
independent of the image size and of thread scheduling) and a 32-bit seed made on the host:

* the per-capture noise (shot, read) from sha256(f"noise|{seed}|{frame}|{camera_key}");
* the FIXED patterns PRNU_ij ~ N(0, prnu) (relative gain, clamped at -1) and DSNU_ij ~ N(0, dsnu_e)
  (electrons) from sha256(f"fpn|{camera_key}") only: the same for every seed and frame of a camera,
  different per camera (`fixed_pattern` returns them). They are drawn into a camera's (gain, offset) arrays
  (`fixed_pattern_arrays`), which the raw kernel reads: a capture draws them once per camera, not once per
  frame (a third of the sensor's time on the mini rig), with the same bits.

Hashes are sha256 (first 8 bytes, folded to 32 bits because Warp seeds are 32-bit), never Python's
`hash()`, so a given (seed, frame, camera_key, inputs) gives byte-identical output on every run.

CPU and CUDA: the arithmetic is float64, compiled without fast math and without floating-point contraction
(no FMA fusion, which the two compilers would place differently), so +, -, *, / and sqrt round identically
on both; only log and exp (libm vs CUDA's libdevice) may differ in the last bit, which moves a quantile
step by ~1e-16 and so changes a count with probability ~1e-16 per draw. With the same float32 radiance the
two devices give the same bytes; a radiance that differs by a few ulps changes a pixel by at most 1 DN.

Vignetting and channel crosstalk act before the sensor and are applied by the caller
(`apply_vignetting`, `apply_crosstalk`, or both from a `Camera` with `apply_optics`; the capture's render
applies them on the device, twin.camera.imaging).
"""
from __future__ import annotations

import hashlib
import math

import numpy as np
import warp as wp

from twin.camera.bayer import cfa_index, cfa_table
from twin.optics.inputs import _init
from twin.rig.camera import SensorParams

wp.set_module_options({"fast_math": False, "fuse_fp": False, "enable_backward": False})  # forward only

POISSON_INVERSION_MAX = 64.0  # electrons: exact inversion below, the Cornish-Fisher quantile at and above
MU_MAX = 1.0e12  # electrons: cap on the mean before sampling
ROW_STRIDE = wp.constant(32768)  # pixel_id = row * ROW_STRIDE + col
MAX_WIDTH = 32768
MAX_HEIGHT = (2**31 - 1) // MAX_WIDTH  # 65535 rows: pixel_id stays a positive int32


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


# --- inverse-CDF variates (float64) -----------------------------------------------------------------
vec8d = wp.types.vector(length=8, dtype=wp.float64)
# Wichura, AS 241 (1988), PPND16: numerators (a, c, e) and denominators (b, d, f), lowest order first
_AS241_A = wp.constant(vec8d(3.3871328727963666080e0, 1.3314166789178437745e+2, 1.9715909503065514427e+3,
                             1.3731693765509461125e+4, 4.5921953931549871457e+4, 6.7265770927008700853e+4,
                             3.3430575583588128105e+4, 2.5090809287301226727e+3))
_AS241_B = wp.constant(vec8d(1.0, 4.2313330701600911252e+1, 6.8718700749205790830e+2, 5.3941960214247511077e+3,
                             2.1213794301586595867e+4, 3.9307895800092710610e+4, 2.8729085735721942674e+4,
                             5.2264952788528545610e+3))
_AS241_C = wp.constant(vec8d(1.42343711074968357734e0, 4.63033784615654529590e0, 5.76949722146069140550e0,
                             3.64784832476320460504e0, 1.27045825245236838258e0, 2.41780725177450611770e-1,
                             2.27238449892691845833e-2, 7.74545014278341407640e-4))
_AS241_D = wp.constant(vec8d(1.0, 2.05319162663775882187e0, 1.67638483018380384940e0, 6.89767334985100004550e-1,
                             1.48103976427480074590e-1, 1.51986665636164571966e-2, 5.47593808499534494600e-4,
                             1.05075007164441684324e-9))
_AS241_E = wp.constant(vec8d(6.65790464350110377720e0, 5.46378491116411436990e0, 1.78482653991729133580e0,
                             2.96560571828504891230e-1, 2.65321895265761230930e-2, 1.24266094738807843860e-3,
                             2.71155556874348757815e-5, 2.01033439929228813265e-7))
_AS241_F = wp.constant(vec8d(1.0, 5.99832206555887937690e-1, 1.36929880922735805310e-1, 1.48753612908506148525e-2,
                             7.86869131145613259100e-4, 1.84631831751005468180e-5, 1.42151175831644588870e-7,
                             2.04426310338993978564e-15))


@wp.func
def _ratio8(num: vec8d, den: vec8d, r: wp.float64):
    """num(r) / den(r), both degree-7 polynomials (Horner)."""
    p = num[7]
    q = den[7]
    for k in range(6, -1, -1):
        p = p * r + num[k]
        q = q * r + den[k]
    return p / q


@wp.func
def normal_quantile(u: wp.float64):
    """Phi^-1(u) for u in (0, 1): AS 241 (PPND16)."""
    q = u - wp.float64(0.5)
    if wp.abs(q) <= wp.float64(0.425):
        return q * _ratio8(_AS241_A, _AS241_B, wp.float64(0.180625) - q * q)
    r = wp.min(u, wp.float64(1.0) - u)
    r = wp.sqrt(-wp.log(r))
    z = wp.float64(0.0)
    if r <= wp.float64(5.0):
        z = _ratio8(_AS241_C, _AS241_D, r - wp.float64(1.6))
    else:
        z = _ratio8(_AS241_E, _AS241_F, r - wp.float64(5.0))
    if q < wp.float64(0.0):
        z = -z
    return z


@wp.func
def uniform52(a: wp.uint32, b: wp.uint32):
    """A uniform in the open interval (0, 1) on the grid (k + 1/2) / 2^52 from two 32-bit draws (exact in
    float64)."""
    k = wp.float64(a >> wp.uint32(6)) * wp.float64(67108864.0) + wp.float64(b >> wp.uint32(6))
    return (k + wp.float64(0.5)) * wp.float64(2.220446049250313e-16)


@wp.func
def poisson_quantile(mu: wp.float64, u: wp.float64):
    """The Poisson(mu) quantile of u (module docstring), as a float64 count; non-decreasing in mu and u."""
    if mu < wp.float64(POISSON_INVERSION_MAX):
        p = wp.exp(-mu)
        cdf = p
        n = wp.float64(0.0)
        # the cap ends the sum where float64 rounding keeps the cdf just below a u within 1e-16 of 1
        cap = mu + wp.float64(12.0) * wp.sqrt(mu) + wp.float64(12.0)
        while cdf < u and n < cap:
            n = n + wp.float64(1.0)
            p = p * mu / n
            cdf = cdf + p
        return n
    z = normal_quantile(u)
    s = wp.sqrt(mu)
    x = mu + s * z + (z * z + wp.float64(2.0)) / wp.float64(6.0) - (z * z * z + wp.float64(2.0) * z) / (
        wp.float64(72.0) * s)
    return wp.max(wp.floor(x), wp.float64(0.0))


# --- the kernels ------------------------------------------------------------------------------------
@wp.struct
class SensorConsts:
    cfa: wp.vec4i  # channel at (row % 2) * 2 + (col % 2)
    e_per_rad: wp.float64  # electrons_per_radiance_s * exposure_s
    dark_e: wp.float64  # dark_current_e_per_s * exposure_s
    read_e: wp.float64
    full_well: wp.float64
    dn_per_e: wp.float64  # 1 / g
    black: wp.float64
    dn_max: wp.float64
    prnu: wp.float64
    dsnu: wp.float64
    mu_max: wp.float64
    noise_seed: int
    fpn_seed: int


@wp.func
def fixed_pattern_at(fpn_seed: int, pid: int, prnu: wp.float64, dsnu: wp.float64):
    """(relative gain 1 + PRNU clamped at 0, DSNU offset in electrons) of one pixel."""
    s = wp.rand_init(fpn_seed, pid)
    gain = wp.max(wp.float64(1.0) + prnu * normal_quantile(uniform52(wp.randu(s), wp.randu(s))), wp.float64(0.0))
    offset = dsnu * normal_quantile(uniform52(wp.randu(s), wp.randu(s)))
    return wp.vec2d(gain, offset)


@wp.kernel
def raw_kernel(rad: wp.array2d(dtype=wp.vec3f), k: SensorConsts, gain: wp.array2d(dtype=wp.float64),
               offset: wp.array2d(dtype=wp.float64), out: wp.array2d(dtype=wp.uint16)):
    i, j = wp.tid()
    pid = i * ROW_STRIDE + j
    c = k.cfa[(i % 2) * 2 + (j % 2)]
    mu = wp.float64(rad[i, j][c]) * k.e_per_rad * gain[i, j] + k.dark_e
    mu = wp.min(wp.max(mu, wp.float64(0.0)), k.mu_max)
    s = wp.rand_init(k.noise_seed, pid)
    n = poisson_quantile(mu, uniform52(wp.randu(s), wp.randu(s)))
    e = n + offset[i, j] + k.read_e * normal_quantile(uniform52(wp.randu(s), wp.randu(s)))
    e = wp.min(e, k.full_well)
    dn = wp.floor(e * k.dn_per_e + k.black + wp.float64(0.5))
    dn = wp.min(wp.max(dn, wp.float64(0.0)), k.dn_max)
    out[i, j] = wp.uint16(int(dn))


@wp.kernel
def fixed_pattern_kernel(fpn_seed: int, prnu: wp.float64, dsnu: wp.float64, gain: wp.array2d(dtype=wp.float64),
                         offset: wp.array2d(dtype=wp.float64)):
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
    """The camera's fixed patterns: (gain (H, W) float64 = 1 + PRNU, offset (H, W) float64 = DSNU in
    electrons), exactly those `simulate_raw` uses for `camera_key`."""
    _check_key(camera_key)
    _check_size(height, width)
    return tuple(a.numpy() for a in _draw_fixed(fixed_pattern_seed(camera_key), float(sensor.prnu),
                                                float(sensor.dsnu_e), height, width, device))


def fixed_pattern_arrays(consts: SensorConsts, height: int, width: int, device) -> tuple[wp.array, wp.array]:
    """The fixed patterns of the camera `consts` were made for (`sensor_consts`; the same for every seed, frame
    and exposure of that camera) as (gain, offset) Warp arrays on `device`, for `raw_frame`."""
    _check_size(height, width)
    return _draw_fixed(consts.fpn_seed, consts.prnu, consts.dsnu, height, width, device)


def _draw_fixed(fpn_seed: int, prnu: float, dsnu: float, height: int, width: int, device):
    _init()
    gain = wp.empty((height, width), dtype=wp.float64, device=device)
    offset = wp.empty((height, width), dtype=wp.float64, device=device)
    wp.launch(fixed_pattern_kernel, dim=(height, width), inputs=[fpn_seed, prnu, dsnu], outputs=[gain, offset],
              device=device)
    return gain, offset


def sensor_consts(sensor: SensorParams, *, exposure_s: float, gain_db: float = 0.0, seed: int, frame: int,
                  camera_key: str) -> SensorConsts:
    """The raw kernel's constants for one frame (checked)."""
    t = _check_exposure(exposure_s)
    for name, v in (("seed", seed), ("frame", frame)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise TypeError(f"{name} must be an integer, got {v!r}")
    _check_key(camera_key)
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
    k.mu_max = float(MU_MAX)
    k.noise_seed = noise_seed(seed, frame, camera_key)
    k.fpn_seed = fixed_pattern_seed(camera_key)
    return k


def raw_frame(radiance: wp.array, consts: SensorConsts, out: wp.array | None = None,
              fixed: tuple[wp.array, wp.array] | None = None) -> wp.array:
    """One raw frame on radiance's device, no host round trip: radiance (H, W) vec3f Warp array
    (non-negative, finite: the caller's guarantee) -> `out` (H, W) uint16 (allocated when None). `fixed`: the
    camera's `fixed_pattern_arrays(consts, H, W, device)`, drawn here when None; a caller taking many frames of
    one camera draws them once."""
    H, W = radiance.shape[:2]
    _check_size(H, W)
    if fixed is None:
        fixed = fixed_pattern_arrays(consts, H, W, radiance.device)
    if len(fixed) != 2 or any(a.shape != (H, W) or a.device != radiance.device for a in fixed):
        raise ValueError(f"fixed patterns must be two ({H}, {W}) arrays on {radiance.device}, got "
                         f"{[(a.shape, str(a.device)) for a in fixed]}")
    if out is None:
        out = wp.empty((H, W), dtype=wp.uint16, device=radiance.device)
    wp.launch(raw_kernel, dim=(H, W), inputs=[radiance, consts, *fixed], outputs=[out], device=radiance.device)
    return out


def simulate_raw(radiance, *, sensor: SensorParams, exposure_s: float, gain_db: float = 0.0, seed: int,
                 frame: int, camera_key: str, device="cpu") -> np.ndarray:
    """One raw frame: radiance (H, W, 3) in the sensor's radiance unit (after vignetting and crosstalk;
    taken as float32) -> uint16 (H, W) digital numbers (see the module docstring for the model).

    Deterministic: the same (radiance, sensor, exposure_s, gain_db, seed, frame, camera_key) give
    byte-identical output."""
    rad = _check_radiance(radiance)
    _check_size(*rad.shape[:2])
    k = sensor_consts(sensor, exposure_s=exposure_s, gain_db=gain_db, seed=seed, frame=frame, camera_key=camera_key)
    _init()
    rad_wp = wp.array(np.ascontiguousarray(rad, dtype=np.float32), dtype=wp.vec3f, device=device)
    return raw_frame(rad_wp, k).numpy()


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


def apply_optics(rgb, camera, flat_field=None, crosstalk: bool = True) -> np.ndarray:
    """Crosstalk then vignetting with a `twin.rig.camera.Camera`'s own sensor parameters: the radiance that
    `simulate_raw` expects for that camera. crosstalk=False: `rgb` is camera RGB already (a scene rendered from
    spectra through the camera's own sensitivities, twin.camera.spectral), so only the vignetting is applied."""
    s = camera.sensor
    return apply_vignetting(apply_crosstalk(rgb, s.crosstalk) if crosstalk else rgb, camera.K, camera.width,
                            camera.height, s.vignetting, flat_field)


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
