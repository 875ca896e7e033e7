"""Noise figures of lighting patterns (docs/designer.md): how precisely a photo pair measures a pattern's
functional, and what multiplexing gains over one-LED-at-a-time (OLAT) photos.

Multiplexing gain (sources)
    Harwit & Sloane, "Hadamard Transform Optics" (Academic Press, 1979): measuring N sources through the
    S-matrix code ((N+1)/2 sources on per frame) instead of one at a time divides the noise variance of each
    estimate by (N+1)^2 / (4N) when the noise does not depend on the light (read noise): gain ~ sqrt(N)/2.
    Wuttig, "Optimal transformations for optical multiplex measurements in the presence of photon noise",
    Applied Optics 44(14), 2710-2719 (2005): with photon (shot) noise growing with the light on, the gain
    falls, to sqrt((N+1)/(2N)) ~ 0.71 (a loss) when shot noise dominates.
    Schechner, Nayar & Belhumeur, "Multiplexing for optimal lighting", IEEE TPAMI 29(8), 1339-1354 (2007):
    the same question for lighting patterns, with the estimate's covariance (W^T Sigma^-1 W)^-1 (Aitken's
    generalised least squares, the best linear unbiased estimate for frame variances Sigma).

Photo noise (ours: the capture plan's photos, twin.capture.plan and twin.camera.hdr)
    A photo of mean radiance B at a pixel is a bracket of exposures t_j (bracket_exposures: BRACKET exposures
    BRACKET_RATIO apart, the shortest putting the photo's brightest radiance at 80% of saturation, clamped
    to EXPOSURE_LIMITS_S and rounded to microseconds), each taken `frames` times in a row and the shortest
    SHORTEST_REPEAT times as often (bracket_frames; the plan's DEFAULT_FRAMES unless given), merged as
    twin.camera.hdr's merge does, frame by frame, with its noise model evaluated at the true radiance (the merge
    evaluates it at its pilot estimate of it):
        mean electrons  mu_j = B k t_j + dark t_j          (k = electrons_per_radiance_s)
        variance        v_j = mu_j + read_noise^2 + g^2 / 12   (shot incl. dark, read, ADC rounding; g e-/DN)
        frame used      mu_j < e_thr = (saturation_threshold_dn - black) g, and for all but the first frame
                        used also mu_j + EXCLUSION_Z sd_j < e_thr, sd_j^2 = mu_j (1 + k t_j / sum k t) + read^2
                        + g^2 / 12 (the sum over the frames used before): the merge's exclusion rule in the mean
        merged variance Var(B^) = 1 / sum_used (k t_j)^2 / v_j   (radiance^2; infinite if no frame is used)
    at the analogue gain of the plan (0 dB). The fixed-pattern terms (PRNU, DSNU) are left out: they are
    per-pixel constants, not noise of a photo. A frame with no LED lit is not photographed: its B is 0 by
    construction (the merge removes the black level and dark signal), so it adds no noise to the pair, and
    its exposures are reported as 0.
"""
from __future__ import annotations

import numpy as np

from twin.camera.hdr import EXCLUSION_Z, saturation_threshold_dn
from twin.camera.sensor import effective_gain
from twin.capture.plan import DEFAULT_FRAMES, bracket_frames, photo_exposures
from twin.rig.camera import SensorParams


def hadamard_gain_closed_form(n: int, read_var_e2, shot_var_e2):
    """Per-source noise gain (sigma_OLAT / sigma_multiplexed) of the S-matrix code of `n` sources (Harwit &
    Sloane 1979; Wuttig 2005): (n+1)/2 sources on per frame, frame variance read_var + (sources on) shot_var,
    G = (n+1) / (2 sqrt n) * sqrt[(read_var + shot_var) / (read_var + (n+1) shot_var / 2)].
    read_var_e2: read-noise variance per frame (e^2); shot_var_e2: shot variance one source adds at full drive
    (e^2, its mean signal in electrons). Limits: read noise only (n+1)/(2 sqrt n) ~ sqrt(n)/2; shot noise only
    sqrt((n+1)/(2n)) ~ 0.71. Scalars or arrays (broadcast)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    k2, eta = np.asarray(read_var_e2, np.float64), np.asarray(shot_var_e2, np.float64)
    for name, v in (("read_var_e2", k2), ("shot_var_e2", eta)):
        if not np.all(np.isfinite(v) & (v >= 0)):
            raise ValueError(f"{name} must be finite and >= 0")
    if np.any(k2 + eta <= 0):
        raise ValueError("read_var_e2 + shot_var_e2 must be positive (a noiseless measurement has no gain)")
    g = (n + 1) / (2 * np.sqrt(n)) * np.sqrt((k2 + eta) / (k2 + (n + 1) * eta / 2))
    return float(g) if g.ndim == 0 else g


def demultiplexing_gain(W, source_signal_e, read_var_e2: float) -> np.ndarray:
    """Per-source noise gain sqrt(var_OLAT / var_demultiplexed) of the frame matrix W (Schechner, Nayar &
    Belhumeur 2007).

    W (F, N): fraction in [0, 1] of source i's drive in frame f, rank N <= F. Source i gives
    source_signal_e[i] electrons at full drive in one frame, so frame f has variance
    sigma_f^2 = read_var_e2 + sum_i W_fi s_i (Poisson + read). The best linear unbiased estimate of the N
    source signals has covariance (W^T Sigma^-1 W)^-1, Sigma = diag(sigma_f^2) (Aitken); one frame per source
    (W = I) has variance read_var_e2 + s_i."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2 or W.shape[0] < W.shape[1] or W.shape[1] < 1:
        raise ValueError(f"W must be an (F, N) matrix with F >= N >= 1, got shape {W.shape}")
    if not np.all(np.isfinite(W)) or W.min() < 0 or W.max() > 1:
        raise ValueError("W must be finite with entries in [0, 1] (fractions of each source's drive)")
    if np.linalg.matrix_rank(W) < W.shape[1]:
        raise ValueError(f"W must have full column rank {W.shape[1]} (every source recoverable)")
    s = np.asarray(source_signal_e, dtype=np.float64)
    if s.shape != (W.shape[1],) or not np.all(np.isfinite(s) & (s >= 0)):
        raise ValueError(f"source_signal_e must be {W.shape[1]} finite values >= 0, got shape {s.shape}")
    k2 = float(read_var_e2)
    if not (np.isfinite(k2) and k2 >= 0):
        raise ValueError(f"read_var_e2 must be finite and >= 0, got {read_var_e2!r}")
    frame_var = k2 + W @ s
    if np.any(frame_var <= 0) or np.any(k2 + s <= 0):
        raise ValueError("read_var_e2 = 0 with a dark frame or source: a noiseless measurement has no gain")
    A = W / np.sqrt(frame_var)[:, None]  # whitened frames
    var_demux = np.diag(np.linalg.inv(A.T @ A))
    return np.sqrt((k2 + s) / var_demux)


def measurement_noise(rig, patterns_signed, lumitexels, sensor: SensorParams, exposures="plan",
                      frames: int = DEFAULT_FRAMES) -> dict:
    """Noise of the measurement y = B(W+) - B(W-) of each signed pattern at M reference texels.

    patterns_signed (K, L) in [-1, 1] over all rig LEDs (W+ = max(w, 0), W- = max(-w, 0)); lumitexels (M, L):
    the radiance one pixel sees from each texel per LED at full drive, so B(W) = sum_l W_l m_l. Each photo
    of a pair is a bracket merged to HDR (module docstring): exposures "plan" brackets each photo from its
    brightest radiance over the M texels (twin.capture.plan.bracket_exposures); a number (seconds) or a
    sequence of them takes every photo at those fixed exposures; either way each exposure is taken `frames`
    times, the shortest SHORTEST_REPEAT times as often (module docstring). y's variance is the sum of its two
    photos'.
    Returns a dict of arrays:
        signal (K, M)        y (radiance)
        sigma (K, M)         its standard deviation; inf where a photo saturates in every frame
        snr (K, M)           |signal| / sigma (0 where sigma is inf)
        saturated (K,)       a photo's shortest exposure saturates at some texel (with the plan: the pattern
                             is too bright for EXPOSURE_LIMITS_S)
        exposures_s (K, 2, T) the (+, -) photos' raw frames' exposures (T = frames_per_photo(frames) with the plan);
                             0 for a photo with no LED lit (not taken)."""
    P = _check_patterns(rig, patterns_signed)
    T = _check_lumitexels(rig, lumitexels)
    _check_sensor(sensor)
    fixed = _check_exposures(exposures)
    Wpm = np.stack([np.clip(P, 0, None), np.clip(-P, 0, None)], axis=1)  # (K, 2, L)
    B = Wpm @ T.T  # (K, 2, M)
    lit = Wpm.any(axis=2)  # (K, 2): frames with some LED on are photographed
    ts, var, sat = _photo_noise(B[lit], fixed, sensor, frames)
    n_t = ts.shape[1]
    exposures_s = np.zeros(lit.shape + (n_t,))
    exposures_s[lit] = ts
    photo_var = np.zeros(B.shape)
    photo_var[lit] = var
    saturated = np.zeros(B.shape, dtype=bool)
    saturated[lit] = sat
    signal = B[:, 0] - B[:, 1]
    sigma = np.sqrt(photo_var.sum(axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(np.isfinite(sigma), np.abs(signal) / sigma, 0.0)
    return {"signal": signal, "sigma": sigma, "snr": snr, "saturated": saturated.any(axis=(1, 2)),
            "exposures_s": exposures_s}


def olat_functional_gain(rig, patterns_signed, lumitexels, sensor: SensorParams, exposures="plan",
                         frames: int = DEFAULT_FRAMES) -> np.ndarray:
    """Per (pattern k, texel m): sigma_OLAT / sigma_multiplexed, where sigma_multiplexed is measurement_noise's
    and sigma_OLAT the standard deviation of the same functional sum_l w_kl m_l assembled from one photo per
    lit LED (LED l alone at full drive, bracketed from its own brightest radiance over the texels with
    exposures "plan", else at the fixed exposures): sigma_OLAT^2 = sum_l w_kl^2 Var(B_l). > 1: the pattern's
    multiplexing beats OLAT (Schechner, Nayar & Belhumeur 2007). A saturated photo has infinite variance, so
    the gain is 0 where only the multiplexed pair saturates, inf where only an OLAT photo does and NaN where
    both do. Arguments as for measurement_noise."""
    P = _check_patterns(rig, patterns_signed)
    T = _check_lumitexels(rig, lumitexels)
    sigma_mux = measurement_noise(rig, P, T, sensor, exposures, frames)["sigma"]
    leds = np.flatnonzero((P != 0).any(axis=0))
    _, var_led, _ = _photo_noise(T[:, leds].T, _check_exposures(exposures), sensor, frames)  # (n_leds, M)
    w2 = P[:, leds] ** 2
    finite = np.isfinite(var_led)
    var_olat = w2 @ np.where(finite, var_led, 0.0)
    var_olat[(w2 > 0) @ ~finite] = np.inf  # a lit LED whose OLAT photo saturates
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(var_olat) / sigma_mux


def _photo_noise(B, fixed, sensor: SensorParams, frames: int):
    """Photos of radiance B (P, M) -> (raw frames' exposures (P, T), merged variance (P, M) radiance^2, shortest
    frame saturated (P, M)), with the plan's brackets (fixed None) or the fixed ascending exposures, taken as the
    plan takes a bracket's (bracket_frames), each exposure's frames in a row: the merge's order (shortest first,
    stable), so its exclusion rule counts the repeats of an exposure among the frames used before."""
    if fixed is None:
        ts = np.array([photo_exposures(float(b.max(initial=0.0)), sensor, frames) for b in B]).reshape(len(B), -1)
    else:
        taken = bracket_frames(list(fixed), frames)
        ts = np.broadcast_to(taken, (len(B), len(taken)))
    g = effective_gain(sensor)  # the plan's analogue gain, 0 dB
    const_var = sensor.read_noise_e ** 2 + g * g / 12.0
    e_thr = (saturation_threshold_dn(sensor) - sensor.black_level_dn) * g
    kt_all = sensor.electrons_per_radiance_s * ts
    kt_sum = np.zeros(B.shape)
    w_sum = np.zeros(B.shape)
    saturated = np.zeros(B.shape, dtype=bool)
    for j in range(ts.shape[1]):  # shortest first, as the merge decides
        kt = kt_all[:, j, None]
        mu = B * kt + sensor.dark_current_e_per_s * ts[:, j, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            sd = np.sqrt(mu * (1.0 + kt / kt_sum) + const_var)
        used = (mu < e_thr) & ((kt_sum <= 0) | (mu + EXCLUSION_Z * sd < e_thr))
        if j == 0:
            saturated = ~used
        kt_sum += np.where(used, kt, 0.0)
        w_sum += np.where(used, kt * kt / (mu + const_var), 0.0)
    with np.errstate(divide="ignore"):
        return np.asarray(ts), 1.0 / w_sum, saturated


def _check_patterns(rig, patterns_signed) -> np.ndarray:
    P = np.asarray(patterns_signed, dtype=np.float64)
    if P.ndim != 2 or P.shape[0] < 1 or P.shape[1] != rig.num_leds:
        raise ValueError(f"patterns_signed must have shape (K, {rig.num_leds}) with K >= 1, got {P.shape}")
    if not np.all(np.isfinite(P)) or np.abs(P).max() > 1:
        raise ValueError("patterns_signed must be finite and lie in [-1, 1]")
    dark = np.flatnonzero(~(P != 0).any(axis=1))
    if dark.size:
        raise ValueError(f"patterns_signed: pattern {dark[0]} lights no LED (nothing to measure)")
    return P


def _check_lumitexels(rig, lumitexels) -> np.ndarray:
    T = np.asarray(lumitexels, dtype=np.float64)
    if T.ndim != 2 or T.shape[0] < 1 or T.shape[1] != rig.num_leds:
        raise ValueError(f"lumitexels must have shape (M, {rig.num_leds}) with M >= 1, got {T.shape}")
    if not np.all(np.isfinite(T)) or T.min() < 0:
        raise ValueError("lumitexels must be finite radiances >= 0")
    return T


def _check_sensor(sensor) -> None:
    if not isinstance(sensor, SensorParams):
        raise ValueError(f"sensor must be a twin.rig.camera.SensorParams, got {type(sensor).__name__}")


def _check_exposures(exposures):
    """None for "plan", else the fixed exposures as an ascending float64 array."""
    if isinstance(exposures, str):
        if exposures != "plan":
            raise ValueError(f"exposures must be 'plan' or exposure times in seconds, got {exposures!r}")
        return None
    t = np.atleast_1d(np.asarray(exposures, dtype=np.float64))
    if t.ndim != 1 or t.size < 1 or not np.all(np.isfinite(t) & (t > 0)):
        raise ValueError(f"exposures must be 'plan' or positive finite seconds (a number or a 1-D sequence), "
                         f"got {exposures!r}")
    return np.sort(t)
