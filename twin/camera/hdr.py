"""Exposure brackets: choosing them and merging raw frames to linear radiance (numpy).

`merge_hdr` inverts `twin.camera.sensor.simulate_raw` frame by frame and combines the frames with noise-optimal
weights. The result is in the unit of simulate_raw's input radiance (the frame's electrons divided by
electrons_per_radiance_s and the exposure).

Per frame k (exposure t_k, electrons per DN g at the common `gain_db`), at every photosite:

    e_k = (DN_k - black) * g - dark_current * t_k          electrons, dark signal removed
    L_k = e_k / (electrons_per_radiance_s * t_k)           the frame's radiance estimate
    valid_k = DN_k < threshold                             threshold = black + (1 - margin) * e_sat / g,
                                                           e_sat = min(full well, ADC range in electrons)

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

Known limitation (measured in tests/test_hdr.py): excluding a frame only when its own reading crosses
the threshold truncates that frame's noise for photosites whose mean lies within ~2 sigma of the
threshold, biasing them low by at most ~0.8 sigma of that frame (about 1% at full well) times its weight
share; photosites away from that band are unbiased.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twin.camera.bayer import demosaic
from twin.rig.camera import SensorParams
from twin.camera.sensor import dn_max, effective_gain, saturation_electrons

DEFAULT_MARGIN = 0.05  # frames above 95% of the saturation signal are excluded


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


def merge_hdr(raws, exposures_s, sensor: SensorParams, gain_db: float = 0.0,
              margin: float = DEFAULT_MARGIN) -> HDRResult:
    """Merge raw frames of one camera (uint16 (H, W) each, the same gain) taken at `exposures_s` into
    linear radiance; see the module docstring."""
    raws = list(raws)
    ts = [float(t) for t in exposures_s]
    if not raws:
        raise ValueError("merge_hdr needs at least one frame")
    if len(raws) != len(ts):
        raise ValueError(f"{len(raws)} frames but {len(ts)} exposures")
    if not all(math.isfinite(t) and t > 0 for t in ts):
        raise ValueError(f"exposures must be positive and finite, got {ts}")
    shape = None
    for i, r in enumerate(raws):
        if not isinstance(r, np.ndarray) or r.dtype != np.uint16 or r.ndim != 2:
            raise TypeError(f"frame {i} must be a uint16 (H, W) numpy array")
        if shape is not None and r.shape != shape:
            raise ValueError(f"frame {i} has shape {r.shape}, frame 0 {shape}")
        shape = r.shape
    if shape[0] < 2 or shape[1] < 2:
        raise ValueError(f"frames must be at least 2x2 to demosaic, got {shape[0]}x{shape[1]}")
    g = effective_gain(sensor, gain_db)
    ke = sensor.electrons_per_radiance_s
    thr = saturation_threshold_dn(sensor, gain_db, margin)
    order = np.argsort(ts, kind="stable")

    # pass 1: pilot radiance from all valid frames (sum of electrons / sum of exposures)
    e_sum = np.zeros(shape)
    kt_sum = np.zeros(shape)
    valid = []
    for r, t in zip(raws, ts):
        v = r < thr
        valid.append(v)
        e = (r.astype(np.float64) - sensor.black_level_dn) * g - sensor.dark_current_e_per_s * t
        e_sum += np.where(v, e, 0.0)
        kt_sum += np.where(v, ke * t, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        L0 = np.maximum(np.where(kt_sum > 0, e_sum / kt_sum, 0.0), 0.0)

    # pass 2: inverse-variance weights from the pilot signal
    num = np.zeros(shape)
    wsum = np.zeros(shape)
    used = np.zeros(shape, dtype=np.uint8)
    const_var = sensor.read_noise_e ** 2 + g * g / 12.0
    for r, t, v in zip(raws, ts, valid):
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
