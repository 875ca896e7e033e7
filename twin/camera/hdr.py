"""Exposure brackets: choosing them and merging raw frames to linear radiance (Warp kernels; numpy oracle).

`merge_hdr` inverts `twin.camera.sensor.simulate_raw` frame by frame and combines the frames with noise-optimal
weights. The result is in the unit of simulate_raw's input radiance (the frame's electrons divided by
electrons_per_radiance_s and the exposure).

Per frame k (exposure t_k, electrons per DN g at the common `gain_db`), at every photosite:

    e_k = (DN_k - black) * g - dark_current * t_k          electrons, dark signal removed
    L_k = e_k / (electrons_per_radiance_s * t_k)           the frame's radiance estimate
    valid_k: frame k is used where its own DN_k < threshold AND, for all but the shortest frame used, the
             mean that the shorter frames already used predict for it stays EXCLUSION_Z (4) standard
             deviations below the threshold: mu_k = L~ k t_k + dark t_k, L~ = sum e / sum k t over those
             frames, sd_k^2 = mu_k (1 + k t_k / sum k t) + read_noise^2 + g^2 / 12 (this frame's noise and the
             prediction's), threshold = black + (1 - margin) * e_sat / g, e_sat = min(full well, ADC range)

Why the prediction (ours, not the paper's): excluding a frame only when its OWN reading crosses the threshold
truncates that frame's noise where its mean lies within ~2 sigma of the threshold and biased those sites
low by up to 0.8 sigma x its weight share (-0.4% measured, tests/test_hdr.py). In a capture that band is
where bright texels of a photo sit in its middle frame, photo by photo, so the bias varied with the light:
on bright, weakly specular samples (ρs/ρd ~ 0.2/0.85: the lobe is 0.5% of a photo) it moved the fitted
roughness by 35% (docs/accuracy.md). The decision from the shorter frames uses noise independent of frame
k's, so a frame kept is unbiased; its cost is the top ~10% of each frame's range (its most precise readings)
where the shorter frames' estimate cannot rule saturation out.

The frames are combined with inverse-variance weights. The variance model of one frame is

    var_e,k = S_k + read_noise^2 + g^2 / 12,    S_k = L0 * k * t_k + dark * t_k (shot noise, electrons)
    Var(L_k) = var_e,k / (k t_k)^2,    weight w_k = 1 / Var(L_k) = (k t_k)^2 / var_e,k   (∝ t^2 / var_e)

with the signal S_k evaluated from a pilot estimate L0 = sum_valid e_k / sum_valid k t_k (the
maximum-likelihood estimate for pure shot noise) rather than from each frame's own noisy value, which
would give low readings larger weights and bias the merge low by about 1/S. The merged site value is
sum_k w_k L_k / sum_k w_k, whose predicted standard deviation is 1 / sqrt(weights_sum).

The merge runs on the raw mosaic (one colour per photosite) and the merged mosaic is demosaiced once
(`twin.camera.bayer.demosaic`, bilinear). This is the brief's "demosaic, divide by exposure, combine" with the
two linear steps swapped: demosaicing each frame first would let a saturated photosite leak into its
unsaturated neighbours' interpolated colours, while on the mosaic every photosite is excluded exactly
in the frames where it is saturated.

A photosite saturated in every frame gets the shortest exposure's clipped estimate (a lower bound),
weight 0, and is flagged in `saturated_mask`; `clipped` flags each demosaiced colour value that depends
on such a photosite.

Where it runs: `merge_kernel` (per photosite, float64) and `demosaic_kernel` (per pixel, float64, then one
rounding to float32) on the frames' device, CPU or CUDA, without contraction (no FMA), so both devices give
the same bytes; `merge_hdr_device` keeps the result there (the capture's photos leave the device only as
files), `merge_hdr` takes and returns numpy. `merge_hdr_numpy` is the numpy implementation this module had
before: the kernels' oracle (tests/test_hdr.py) and the same-work baseline of `hemicube bench capture`.

Remaining truncation: the shortest frame used is still excluded by its own reading, which matters only where
it sits within ~2 sigma of the threshold, i.e. where every frame saturates but the shortest; and a kept frame
whose own reading crosses the threshold (probability ~3e-5 at EXCLUSION_Z = 4) is dropped.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from twin.camera.bayer import cfa_table, demosaic
from twin.rig.camera import SensorParams
from twin.camera.sensor import dn_max, effective_gain, saturation_electrons

wp.set_module_options({"fast_math": False, "fuse_fp": False, "enable_backward": False})  # forward only

DEFAULT_MARGIN = 0.05  # frames above 95% of the saturation signal are excluded
MAX_FRAMES = 16  # frames per merge (the plan's brackets have 3)
EXCLUSION_Z = 4.0  # a longer frame is used only where the shorter ones predict it EXCLUSION_Z sd below saturation


@dataclass(frozen=True)
class HDRResult:
    """radiance (H, W, 3) float32: merged, demosaiced radiance.
    saturated_mask (H, W) bool: photosites saturated in every frame (their value is a lower bound).
    weights_sum (H, W) float32: per photosite, sum of the inverse-variance weights = 1 / predicted
        variance of `mosaic` (radiance^-2); 0 where saturated everywhere.
    mosaic (H, W) float32: merged radiance of each photosite (the colour of its filter).
    clipped (H, W, 3) bool: demosaiced values that depend on a photosite saturated everywhere.
    frames_used (H, W) uint8: how many frames each photosite took."""

    radiance: np.ndarray
    saturated_mask: np.ndarray
    weights_sum: np.ndarray
    mosaic: np.ndarray | None = None
    clipped: np.ndarray | None = None
    frames_used: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray:
        """Predicted standard deviation of `mosaic` (inf where saturated everywhere)."""
        with np.errstate(divide="ignore"):
            return 1.0 / np.sqrt(self.weights_sum.astype(np.float64))


def saturation_threshold_dn(sensor: SensorParams, gain_db: float = 0.0, margin: float = DEFAULT_MARGIN) -> float:
    """Raw values at or above this are treated as saturated: black + (1 - margin) * e_sat / g."""
    if not (0.0 <= margin < 1.0):
        raise ValueError(f"margin must be in [0, 1), got {margin}")
    g = effective_gain(sensor, gain_db)
    return min(sensor.black_level_dn + (1.0 - margin) * saturation_electrons(sensor, gain_db) / g,
               float(dn_max(sensor)))


def frame_radiance(raw, exposure_s: float, sensor: SensorParams, gain_db: float = 0.0) -> np.ndarray:
    """One frame's per-photosite radiance estimate (float64 (H, W)): black, gain, dark and exposure removed."""
    g = effective_gain(sensor, gain_db)
    e = (np.asarray(raw, dtype=np.float64) - sensor.black_level_dn) * g - sensor.dark_current_e_per_s * exposure_s
    return e / (sensor.electrons_per_radiance_s * exposure_s)


@wp.struct
class MergeConsts:
    cfa: wp.vec4i  # channel at (row % 2) * 2 + (col % 2)
    frames: int
    exposure: wp.types.vector(length=MAX_FRAMES, dtype=wp.float64)
    shortest: int
    order: wp.types.vector(length=MAX_FRAMES, dtype=wp.int32)  # frames by ascending exposure (stable)
    black: wp.float64
    g: wp.float64  # electrons per DN
    dark: wp.float64  # electrons per second
    ke: wp.float64  # electrons per radiance-second
    threshold: wp.float64  # DN: at or above, the frame is saturated at this site
    const_var: wp.float64  # read noise^2 + g^2 / 12
    e_threshold: wp.float64  # electrons above black at the threshold: (threshold - black) * g
    z: wp.float64  # EXCLUSION_Z


@wp.func
def _frame_radiance(dn: wp.float64, t: wp.float64, k: MergeConsts):
    return ((dn - k.black) * k.g - k.dark * t) / (k.ke * t)


@wp.func
def _use_frame(r: wp.float64, t: wp.float64, e_acc: wp.float64, kt_acc: wp.float64, k: MergeConsts):
    """Whether a frame whose DN is r and exposure t is used, given the electrons e_acc and k t sum kt_acc of
    the shorter frames used so far (module docstring: valid_k)."""
    if r >= k.threshold:
        return False
    if kt_acc <= wp.float64(0.0):
        return True
    kt = k.ke * t
    mu = wp.max(e_acc / kt_acc, wp.float64(0.0)) * kt + k.dark * t
    sd = wp.sqrt(mu * (wp.float64(1.0) + kt / kt_acc) + k.const_var)
    return mu + k.z * sd < k.e_threshold


@wp.kernel
def merge_kernel(raw: wp.array3d(dtype=wp.uint16), k: MergeConsts, mosaic: wp.array2d(dtype=wp.float64),
                 weights_sum: wp.array2d(dtype=wp.float32), used: wp.array2d(dtype=wp.uint8),
                 saturated: wp.array2d(dtype=wp.uint8), saturated_count: wp.array(dtype=int)):
    """One photosite: the frames used, shortest first, and the pilot estimate from them; then the
    inverse-variance merge of the same frames (module docstring; the numpy twin is merge_hdr_numpy)."""
    i, j = wp.tid()
    zero = wp.float64(0.0)
    e_sum = zero
    kt_sum = zero
    for o in range(k.frames):
        f = k.order[o]
        r = wp.float64(raw[f, i, j])
        t = k.exposure[f]
        if _use_frame(r, t, e_sum, kt_sum, k):
            e_sum += (r - k.black) * k.g - k.dark * t
            kt_sum += k.ke * t
    L0 = zero
    if kt_sum > zero:
        L0 = wp.max(e_sum / kt_sum, zero)
    num = zero
    wsum = zero
    n = int(0)
    e_acc = zero  # the same decisions again, in the same order
    kt_acc = zero
    for o in range(k.frames):
        f = k.order[o]
        r = wp.float64(raw[f, i, j])
        t = k.exposure[f]
        if _use_frame(r, t, e_acc, kt_acc, k):
            kt = k.ke * t
            e_acc += (r - k.black) * k.g - k.dark * t
            kt_acc += kt
            w = kt * kt / (L0 * kt + k.dark * t + k.const_var)
            num += w * _frame_radiance(r, t, k)
            wsum += w
            n += 1
    if n == 0:  # saturated in every frame: the shortest exposure's clipped estimate, a lower bound
        mosaic[i, j] = _frame_radiance(wp.float64(raw[k.shortest, i, j]), k.exposure[k.shortest], k)
        saturated[i, j] = wp.uint8(1)
        wp.atomic_add(saturated_count, 0, 1)
    else:
        mosaic[i, j] = num / wsum
        saturated[i, j] = wp.uint8(0)
    weights_sum[i, j] = wp.float32(wsum)
    used[i, j] = wp.uint8(n)


@wp.func
def _reflect(i: int, n: int):
    """numpy's "reflect" padding by one: -1 -> 1, n -> n - 2."""
    if i < 0:
        return -i
    if i > n - 1:
        return 2 * (n - 1) - i
    return i


@wp.kernel
def demosaic_kernel(mosaic: wp.array2d(dtype=wp.float64), saturated: wp.array2d(dtype=wp.uint8), cfa: wp.vec4i,
                    rgb: wp.array2d(dtype=wp.vec3f), clipped: wp.array2d(dtype=wp.vec3ub)):
    """Bilinear demosaicing of one pixel (twin.camera.bayer.demosaic's 3x3 kernels and reflected border, in
    its order of summation) of the merged mosaic, and of the saturation mask (-> `clipped`)."""
    i, j = wp.tid()
    H = mosaic.shape[0]
    W = mosaic.shape[1]
    out = wp.vec3d()
    clip = wp.vec3ub()
    for c in range(3):
        acc = wp.float64(0.0)
        sat = wp.float64(0.0)
        for di in range(3):
            for dj in range(3):
                # the kernels: green 1/4 [[0,1,0],[1,4,1],[0,1,0]], red and blue 1/4 [[1,2,1],[2,4,2],[1,2,1]]
                wk = wp.float64(0.0)
                if c == 1:
                    if di == 1 and dj == 1:
                        wk = wp.float64(1.0)
                    elif di == 1 or dj == 1:
                        wk = wp.float64(0.25)
                else:
                    if di == 1 and dj == 1:
                        wk = wp.float64(1.0)
                    elif di == 1 or dj == 1:
                        wk = wp.float64(0.5)
                    else:
                        wk = wp.float64(0.25)
                ii = _reflect(i + di - 1, H)
                jj = _reflect(j + dj - 1, W)
                if wk != wp.float64(0.0) and cfa[(ii % 2) * 2 + (jj % 2)] == c:
                    acc += wk * mosaic[ii, jj]
                    sat += wk * wp.float64(saturated[ii, jj])
        out[c] = acc
        if sat > wp.float64(0.0):
            clip[c] = wp.uint8(1)
    rgb[i, j] = wp.vec3f(out)
    clipped[i, j] = clip


def _merge_consts(ts: list[float], sensor: SensorParams, gain_db: float, margin: float) -> MergeConsts:
    g = effective_gain(sensor, gain_db)
    k = MergeConsts()
    k.cfa = wp.vec4i(*[int(v) for v in cfa_table(sensor.bayer).ravel()])
    k.frames = len(ts)
    k.exposure = wp.types.vector(length=MAX_FRAMES, dtype=wp.float64)(*(ts + [1.0] * (MAX_FRAMES - len(ts))))
    order = [int(v) for v in np.argsort(ts, kind="stable")]
    k.shortest = order[0]
    k.order = wp.types.vector(length=MAX_FRAMES, dtype=wp.int32)(*(order + [0] * (MAX_FRAMES - len(ts))))
    k.black = float(sensor.black_level_dn)
    k.g = float(g)
    k.dark = float(sensor.dark_current_e_per_s)
    k.ke = float(sensor.electrons_per_radiance_s)
    k.threshold = float(saturation_threshold_dn(sensor, gain_db, margin))
    k.const_var = float(sensor.read_noise_e ** 2 + g * g / 12.0)
    k.e_threshold = float((k.threshold - k.black) * g)
    k.z = EXCLUSION_Z
    return k


def _check_exposures(n: int, exposures_s) -> list[float]:
    ts = [float(t) for t in exposures_s]
    if n == 0:
        raise ValueError("merge_hdr needs at least one frame")
    if n != len(ts):
        raise ValueError(f"{n} frames but {len(ts)} exposures")
    if n > MAX_FRAMES:
        raise ValueError(f"merge_hdr takes at most {MAX_FRAMES} frames, got {n}")
    if not all(math.isfinite(t) and t > 0 for t in ts):
        raise ValueError(f"exposures must be positive and finite, got {ts}")
    return ts


def merge_hdr_device(raws: wp.array, exposures_s, sensor: SensorParams, gain_db: float = 0.0,
                     margin: float = DEFAULT_MARGIN) -> dict:
    """The merge on the frames' device: raws (n, H, W) uint16 Warp array -> Warp arrays there: "radiance"
    (H, W) vec3f, "mosaic" (H, W) float64, "weights_sum" float32, "frames_used" uint8, "saturated" uint8,
    "clipped" (H, W) vec3ub, and "saturated_count" (1,) int (sites saturated in every frame)."""
    n, H, W = raws.shape
    ts = _check_exposures(n, exposures_s)
    if H < 2 or W < 2:
        raise ValueError(f"frames must be at least 2x2 to demosaic, got {H}x{W}")
    k = _merge_consts(ts, sensor, gain_db, margin)
    dev = raws.device
    out = {"mosaic": wp.empty((H, W), dtype=wp.float64, device=dev),
           "weights_sum": wp.empty((H, W), dtype=wp.float32, device=dev),
           "frames_used": wp.empty((H, W), dtype=wp.uint8, device=dev),
           "saturated": wp.empty((H, W), dtype=wp.uint8, device=dev),
           "saturated_count": wp.zeros(1, dtype=int, device=dev),
           "radiance": wp.empty((H, W), dtype=wp.vec3f, device=dev),
           "clipped": wp.empty((H, W), dtype=wp.vec3ub, device=dev)}
    wp.launch(merge_kernel, dim=(H, W), inputs=[raws, k],
              outputs=[out[f] for f in ("mosaic", "weights_sum", "frames_used", "saturated", "saturated_count")],
              device=dev)
    wp.launch(demosaic_kernel, dim=(H, W), inputs=[out["mosaic"], out["saturated"], k.cfa],
              outputs=[out["radiance"], out["clipped"]], device=dev)
    return out


def _check_frames(raws) -> list[np.ndarray]:
    raws = list(raws)
    shape = None
    for i, r in enumerate(raws):
        if not isinstance(r, np.ndarray) or r.dtype != np.uint16 or r.ndim != 2:
            raise TypeError(f"frame {i} must be a uint16 (H, W) numpy array")
        if shape is not None and r.shape != shape:
            raise ValueError(f"frame {i} has shape {r.shape}, frame 0 {shape}")
        shape = r.shape
    return raws


def merge_hdr(raws, exposures_s, sensor: SensorParams, gain_db: float = 0.0,
              margin: float = DEFAULT_MARGIN, device="cpu") -> HDRResult:
    """Merge raw frames of one camera (uint16 (H, W) numpy arrays, the same gain) taken at `exposures_s` into
    linear radiance; see the module docstring. Runs the kernels on `device`; numpy results."""
    raws = _check_frames(raws)
    _check_exposures(len(raws), exposures_s)
    from twin.optics.inputs import _init

    _init()
    r = merge_hdr_device(wp.array(np.stack(raws), dtype=wp.uint16, device=device), exposures_s, sensor, gain_db,
                         margin)
    return HDRResult(radiance=r["radiance"].numpy(), saturated_mask=r["saturated"].numpy().astype(bool),
                     weights_sum=r["weights_sum"].numpy(), mosaic=r["mosaic"].numpy().astype(np.float32),
                     clipped=r["clipped"].numpy().astype(bool), frames_used=r["frames_used"].numpy())


def merge_hdr_numpy(raws, exposures_s, sensor: SensorParams, gain_db: float = 0.0,
                    margin: float = DEFAULT_MARGIN) -> HDRResult:
    """`merge_hdr` in numpy (the kernels' oracle and the capture bench's baseline)."""
    raws = _check_frames(raws)
    ts = _check_exposures(len(raws), exposures_s)
    shape = raws[0].shape
    if shape[0] < 2 or shape[1] < 2:
        raise ValueError(f"frames must be at least 2x2 to demosaic, got {shape[0]}x{shape[1]}")
    g = effective_gain(sensor, gain_db)
    ke = sensor.electrons_per_radiance_s
    thr = saturation_threshold_dn(sensor, gain_db, margin)
    order = np.argsort(ts, kind="stable")

    const_var = sensor.read_noise_e ** 2 + g * g / 12.0
    e_thr = (thr - sensor.black_level_dn) * g

    # pass 1: the frames used at each site, shortest first (merge_kernel's _use_frame), and the pilot radiance
    # from them (sum of electrons / sum of exposures)
    e_sum, kt_sum = np.zeros(shape), np.zeros(shape)
    valid = {}
    for f in order:
        r, t = raws[f], ts[f]
        kt = ke * t
        with np.errstate(invalid="ignore", divide="ignore"):
            mu = np.maximum(e_sum / kt_sum, 0.0) * kt + sensor.dark_current_e_per_s * t
            sd = np.sqrt(mu * (1.0 + kt / kt_sum) + const_var)
        v = valid[f] = (r < thr) & ((kt_sum <= 0) | (mu + EXCLUSION_Z * sd < e_thr))
        e = (r.astype(np.float64) - sensor.black_level_dn) * g - sensor.dark_current_e_per_s * t
        e_sum += np.where(v, e, 0.0)
        kt_sum += np.where(v, kt, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        L0 = np.maximum(np.where(kt_sum > 0, e_sum / kt_sum, 0.0), 0.0)

    # pass 2: inverse-variance weights from the pilot signal
    num = np.zeros(shape)
    wsum = np.zeros(shape)
    used = np.zeros(shape, dtype=np.uint8)
    for f in order:  # the kernel's order of summation
        r, t, v = raws[f], ts[f], valid[f]
        kt = ke * t
        var_e = L0 * kt + sensor.dark_current_e_per_s * t + const_var
        w = np.where(v, kt * kt / var_e, 0.0)
        num += w * frame_radiance(r, t, sensor, gain_db)
        wsum += w
        used += v
    sat_all = used == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mos = np.where(sat_all, 0.0, num / np.where(sat_all, 1.0, wsum))
    shortest = int(order[0])
    mos = np.where(sat_all, frame_radiance(raws[shortest], ts[shortest], sensor, gain_db), mos)

    rgb = demosaic(mos, sensor.bayer)
    clipped = demosaic(sat_all.astype(np.float64), sensor.bayer) > 0
    return HDRResult(radiance=rgb.astype(np.float32), saturated_mask=sat_all, weights_sum=wsum.astype(np.float32),
                     mosaic=mos.astype(np.float32), clipped=clipped, frames_used=used)


def choose_bracket(max_radiance: float, sensor: SensorParams, n: int = 3, ratio: float = 8.0,
                   gain_db: float = 0.0, fill: float = 0.8) -> list[float]:
    """`n` exposures (seconds, ascending, each `ratio` times the last) whose shortest puts `max_radiance`
    at `fill` (80%) of the saturation signal (full well, or the ADC top if that comes first)."""
    L = float(max_radiance)
    if not (math.isfinite(L) and L > 0):
        raise ValueError(f"max_radiance must be positive and finite, got {max_radiance}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    if not (math.isfinite(ratio) and ratio > 1):
        raise ValueError(f"ratio must be > 1, got {ratio}")
    if not (0 < fill < 1):
        raise ValueError(f"fill must be in (0, 1), got {fill}")
    e_target = fill * saturation_electrons(sensor, gain_db)
    t0 = e_target / (L * sensor.electrons_per_radiance_s + sensor.dark_current_e_per_s)
    return [t0 * ratio ** i for i in range(int(n))]


def still_photo(radiance, camera, *, seed: int, frames: int, camera_key: str, first_frame: int = 0,
                fill: float = 0.6, flat_field=None, camera_rgb: bool = False,
                device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """A photo of a static scene, as a calibration takes one: `radiance` (H, W, 3, scene radiance before the
    optics) through `camera`'s crosstalk and falloff (twin.camera.sensor.apply_optics, with the per-pixel
    `flat_field` factor if given) and sensor, `frames` raw frames at the one exposure that puts the brightest
    photosite's mean at `fill` of saturation, each merged alone and then averaged (averaging frames beats the
    shot noise down; one exposure suffices for a scene without highlights). The frames' noise draws are
    frames first_frame, first_frame + 1, ... of `seed` for `camera_key` (whose fixed patterns they share, as
    photos of one sensor do). camera_rgb: `radiance` is camera RGB already (rendered from spectra,
    twin.camera.spectral), so the crosstalk is not applied again. Returns the (H, W, 3) float64
    mean radiance and the (H, W) mask of photosites saturated in any frame."""
    from twin.camera.sensor import apply_optics, simulate_raw

    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ValueError(f"frames must be a positive integer, got {frames!r}")
    rad = apply_optics(np.asarray(radiance, np.float64), camera, flat_field, crosstalk=not camera_rgb)
    t = choose_bracket(float(rad.max()), camera.sensor, n=1, fill=fill)[0]
    total, saturated = np.zeros(rad.shape), np.zeros(rad.shape[:2], bool)
    for k in range(int(frames)):
        raw = simulate_raw(rad, sensor=camera.sensor, exposure_s=t, seed=seed, frame=first_frame + k,
                           camera_key=camera_key, device=device)
        merged = merge_hdr([raw], [t], camera.sensor, device=device)
        total += merged.radiance
        saturated |= merged.saturated_mask
    return total / frames, saturated

