"""Is a photo plausible? Judged only from what a real capture has, never from the twin's ground truth: the
LED controller's acknowledgement around the metering (twin.capture.backends.hardware: a photo is metered
under the pattern the controller acknowledged, else the LEDs are lit again and it is metered again, at most
METER_ATTEMPTS times), then the bracket's own exposures and raw levels (`judge_bracket`, here). The capture
loop (twin.capture.runner.photos) takes an implausible photo again, at most PHOTO_ATTEMPTS times, then stops
with one line that names it. docs/reliability.md states the bounds and what they were measured against.

A photo's bracket is planned from its metering (twin.capture.plan.bracket_exposures): the shortest exposure
puts the brightest radiance metered at 80 % of the saturation signal (twin.camera.hdr.choose_bracket), the
others BRACKET_RATIO times longer each. When the metering and the frames saw the same light:

  saturation  almost no photosite saturates in every frame: only noise above the brightest photosite's 80 %
              can. A bracket metered in the dark and taken in the light (a controller reset between the
              metering and the frames, the LEDs lit again for the frames) is exposed for darkness: 16 x 1.0 s,
              96 % of the photosites saturated. Not judged when the shortest exposure is the camera's shortest
              (EXPOSURE_LIMITS_S): a scene brighter than the camera can take saturates whatever was metered.
  levels      a raw level above black is proportional to the exposure (twin.camera.sensor: the mean
              photo-electrons, dark current included, are proportional to t): over the photosites that no
              frame of two consecutive exposures saturates and where the shorter one's mean level is
              SIGNAL_FLOOR_DN above black, the longer exposure's summed level over the shorter's is their
              exposure ratio. Lights that changed between the exposures, a camera that applied another
              exposure than it reports, or frames of another scene break it. Judged where at least
              MIN_COMPARED photosites qualify (a dark photo has too few: only its saturation is judged).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from twin.capture.plan import EXPOSURE_LIMITS_S

# A photo saturated in every frame on more than 1 % of its photosites is refused. The clean captures of every
# suite sample have none (docs/reliability.md); the fault in the docstring has 96 %. 1 % leaves a real camera's
# metering (from preview frames, twin.capture.backends.pylon_cameras) room to miss a small highlight.
MAX_SATURATED_SHARE = 0.01
# The levels of two exposures may differ from their exposure ratio by 10 %. Clean captures of every suite sample
# stay within 0.2 % (docs/reliability.md); lights that changed mid-bracket move it by a factor.
LEVEL_RATIO_TOLERANCE = 0.10
SIGNAL_FLOOR_DN = 32  # ~75 e- on the a2A5328-15ucPRO's 2.4 e-/DN: read noise (2.3 e-) and DSNU are < 4 % of it
MIN_COMPARED = 100  # photosites: below, a ratio of sums is decided by a few pixels' noise
# A photo is taken at most 3 times (a bracket refused by these checks costs one bracket; a fault that repeats
# three times is not a passing one), and metered at most 4 times: a reset during the metering costs a metering
# and a latch, and with a controller that browns out after 25 % of its latches (`hemicube bench metering-faults`)
# a photo whose metering was hit is refused only when the next three latches brown out too (1.6 %).
PHOTO_ATTEMPTS = 3
METER_ATTEMPTS = 4


@dataclass(frozen=True)
class Judgement:
    """saturated_share: photosites saturated in every frame, of all; level_ratios: per pair of consecutive
    exposures, the longer's summed level over the shorter's divided by their exposure ratio (None: too few
    photosites to judge); reason: why the photo is implausible, or None."""

    saturated_share: float
    level_ratios: tuple
    reason: str | None


def _duration(t: float) -> str:
    return f"{t:g} s" if t >= 1 else f"{t * 1e3:g} ms"


def _exposures_text(exposures_s) -> str:
    """'8 x 3.197 ms, 4 x 25.576 ms': the exposures in the order taken, repeats counted."""
    runs: list[list] = []
    for t in exposures_s:
        if runs and runs[-1][0] == t:
            runs[-1][1] += 1
        else:
            runs.append([t, 1])
    return ", ".join(f"{n} x {_duration(t)}" for t, n in runs)


def judge_bracket(raws, exposures_s, sensor) -> Judgement:
    """A photo's raw frames ((n, H, W) uint16 Warp array, any device) at `exposures_s` (as the camera applied
    them), judged as the module docstring says. Integer sums on the frames' device: the same verdict on every
    device."""
    import torch
    import warp as wp

    from twin.camera.hdr import saturation_threshold_dn

    ts = [float(t) for t in exposures_s]
    r = wp.to_torch(raws)
    _, H, W = r.shape
    thr = saturation_threshold_dn(sensor)
    black = float(sensor.black_level_dn)
    groups = sorted(set(ts))
    level = {t: torch.zeros((H, W), dtype=torch.int32, device=r.device) for t in groups}  # summed DN
    unsaturated = {t: torch.ones((H, W), dtype=torch.bool, device=r.device) for t in groups}
    everywhere = torch.ones((H, W), dtype=torch.bool, device=r.device)
    for f, t in enumerate(ts):
        frame = r[f].view(torch.int16).to(torch.int32) & 0xFFFF  # torch's uint16 conversion is a slow path
        saturated = frame >= thr
        everywhere &= saturated
        level[t] += frame
        unsaturated[t] &= ~saturated
    share = int(everywhere.sum()) / (H * W)
    count = {t: ts.count(t) for t in groups}
    ratios = []
    for a, b in zip(groups, groups[1:]):
        ok = unsaturated[a] & unsaturated[b] & (level[a] >= (black + SIGNAL_FLOOR_DN) * count[a])
        m = int(ok.sum())
        if m < MIN_COMPARED:
            ratios.append(None)
            continue
        above = [int(level[t][ok].sum(dtype=torch.int64)) / count[t] - black * m for t in (a, b)]
        ratios.append(above[1] / above[0] / (b / a))
    reason = None
    if share > MAX_SATURATED_SHARE and min(ts) > EXPOSURE_LIMITS_S[0]:
        reason = (f"{share:.1%} of its photosites saturated in every frame (at most {MAX_SATURATED_SHARE:.0%}; "
                  f"exposures {_exposures_text(ts)})")
    else:
        for (a, b), q in zip(zip(groups, groups[1:]), ratios):
            if q is not None and not (math.isfinite(q) and abs(q - 1) <= LEVEL_RATIO_TOLERANCE):
                reason = (f"its level at {_duration(b)} is {q:.3g} x what its level at {_duration(a)} and the "
                          f"exposures imply (within {LEVEL_RATIO_TOLERANCE:.0%})")
                break
    return Judgement(share, tuple(ratios), reason)
