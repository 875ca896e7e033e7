"""The capture plan (reference §6.3 indices, extended by the photos the reference takes separately):

    k 0-63     learned patterns as 32 (+, -) pairs          cameras 0 and 1
    k 64-127   the 64 linear lights                         camera 0
    k 128      all bottom LEDs (transparency)               camera 0
    k 129      uniform light (two-view alignment)           cameras 0 and 1
    k 130      all bottom LEDs, empty board (reference for transparency: transparency = k128 / k130)

With another number of learned patterns K (a capture design, docs/designer.md: F = 2K learned frames), the same
order shifts: learned 0..F-1, lines F..F+63, then bottom, uniform, empty bottom (`PlanIndices`); a capture
records which pattern each photo showed, so `indices_of(session)` reads its layout back. K = 32 is the
reference's layout (`REFERENCE_INDICES`).

Each photo is an exposure bracket of BRACKET exposures, BRACKET_RATIO apart, the longer ones each taken `frames`
times and the shortest SHORTEST_REPEAT times as often (DEFAULT_FRAMES unless asked otherwise; `bracket_frames`),
merged to linear HDR (twin.camera.hdr: repeated frames of one exposure are averaged by its inverse-variance weights,
so N frames cut the temporal noise by sqrt(N)). The learned frames default to the patterns a rig carries as data
(DEFAULT_PATTERNS: the shipped network's for the built-in rigs, written there by reconstruction.network.shipped), else a
seeded placeholder; `twin` never asks the network for them.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from twin.capture import pattern_sets
from twin.capture.pattern_sets import NUM_LINEAR_LIGHTS
from twin.capture.patterns import load_patterns
from twin.rig.builtin import serves_for

BRACKET = 3  # exposures per photo
BRACKET_RATIO = 8.0
# frames a photo may take in all: frame_id gives each (photo, camera) 16 streams of sensor noise,
MAX_FRAMES_PER_PHOTO = 16  # and the HDR merge takes 16 frames at most (twin.camera.hdr.MAX_FRAMES)
# Four frames an exposure by default (ours): a weak, rough lobe (fabric's, paper stock's: 0.5-2% of a photo) is
# decided by the photos' temporal noise, and averaging four frames halves it; measured on the whole material suite,
# every alpha, rho_d and normal median improved and fabric's compositions met the goals (docs/accuracy.md). The real
# device takes each exposure four times, the shortest eight (docs/performance.md has the capture times).
DEFAULT_FRAMES = 4
# the capture's seed (sensor noise, seeded samples) when none is given: the same for `hemicube capture`,
# `capture-many` and `validate`, whose documented figures use it (docs/accuracy.md)
DEFAULT_SEED = 1
# The shortest exposure is taken twice as often (ours): it alone measures the brightest part of a photo, which
# saturates the longer ones, so that part had a third of the photo's frames; on a bright stock (paper's, rho_d ~0.85)
# that is where a weak lobe is, measured by 20,000 e- a photosite (0.6-0.9% shot noise; docs/accuracy.md). The extra
# frames are the bracket's shortest: 4 more frames add 4 / (4 x 73) of a photo's exposure time (ratio 8: 1 + 8 + 64).
SHORTEST_REPEAT = 2
# the largest `frames` whose photo the 16 frame streams hold
MAX_FRAMES_PER_EXPOSURE = MAX_FRAMES_PER_PHOTO // (BRACKET - 1 + SHORTEST_REPEAT)
EXPOSURE_LIMITS_S = (20e-6, 1.0)  # the camera's exposure range used by the plan (a2A5328-15ucPRO: 20 us up)
# Exposures are planned in whole microseconds, the unit cameras take them in (ExposureTime), so that a camera
# (pylon's emulator included) applies exactly what was planned; the HDR merge uses what the camera reports.
# (n / 1e6 is the double nearest to n microseconds, the same number whichever code converts it)
EXPOSURE_STEPS_PER_S = 1_000_000


@dataclass(frozen=True)
class PlanIndices:
    """Photo indices of a plan with `learned_frames` (2K) learned frames (module docstring)."""

    learned_frames: int = 64

    def __post_init__(self):
        f = self.learned_frames
        if isinstance(f, bool) or not isinstance(f, int) or f < 2 or f % 2:
            raise CaptureError(f"the plan takes learned patterns as (+, -) pairs: an even number >= 2 of learned "
                               f"frames, got {f!r}")

    @property
    def learned(self) -> range:
        return range(0, self.learned_frames)

    @property
    def lines(self) -> range:
        return range(self.learned_frames, self.learned_frames + NUM_LINEAR_LIGHTS)

    @property
    def bottom(self) -> int:
        return self.learned_frames + NUM_LINEAR_LIGHTS

    @property
    def uniform(self) -> int:
        return self.bottom + 1

    @property
    def empty_bottom(self) -> int:
        return self.bottom + 2


def indices_of(session) -> PlanIndices:
    """The plan layout of a capture, from the patterns its camera-0 photos showed (the first line photo
    follows the learned frames)."""
    shown = session.shown_patterns(0)
    lines = [k for k, name in shown.items() if name.startswith("line_")]
    if not lines:
        raise CaptureError(f"{session.dir}: its plan has no line photos")
    ix = PlanIndices(min(lines))
    if any(k not in shown for k in ix.learned):
        raise CaptureError(f"{session.dir}: its plan lacks learned photos below index {ix.learned_frames}")
    return ix


REFERENCE_INDICES = PlanIndices(64)  # the reference's plan (reference §6.3): 32 signed pairs

# per rig name: the learned patterns it carries, and the digest of the rig they were made for
DEFAULT_PATTERNS = Path(__file__).resolve().parent / "default_patterns"


class CaptureError(ValueError):
    pass


class DeviceError(CaptureError):
    """A device (the LED controller, a camera) that still failed after its retries, or cannot be used."""


@dataclass(frozen=True)
class Photo:
    index: int
    camera: str
    camera_index: int
    pattern: str
    sample: str  # "sample" or "empty"


def default_learned(rig):
    """The learned frames a rig carries (DEFAULT_PATTERNS/index.toml names the file and the rig digest they
    were made for), or None."""
    index = DEFAULT_PATTERNS / "index.toml"
    entry = tomllib.loads(index.read_text()).get(rig.name) if index.is_file() else None
    if entry is None or not serves_for(rig, entry["rig_digest"]):  # a vignetting calibration keeps them
        return None
    return load_patterns(DEFAULT_PATTERNS / entry["file"])


def build_patterns(rig, learned=None):
    """The plan's pattern set: the learned frames given, else the rig's default ones, else a seeded
    placeholder."""
    if learned is None:
        learned = default_learned(rig) or pattern_sets.placeholder_learned(rig)
    PlanIndices(learned.num_patterns)  # any K, as (+, -) pairs: an even count
    sets = [learned, pattern_sets.linear_lights(rig), pattern_sets.uniform(rig)]
    if rig.is_bottom.any():
        sets.append(pattern_sets.bottom_only(rig))
    return pattern_sets.concatenate(sets, rig.name, note=learned.note)


def paper_plan(rig, patterns) -> list[Photo]:
    cams = list(rig.cameras)
    names = patterns.names
    ix = PlanIndices(names.index("line_00"))  # the learned frames come first (build_patterns)
    plan = []
    for k in ix.learned:
        plan += [Photo(k, cams[c], c, names[k], "sample") for c in range(len(cams))]
    plan += [Photo(k, cams[0], 0, f"line_{j:02d}", "sample") for j, k in enumerate(ix.lines)]
    if "bottom" in names:
        plan.append(Photo(ix.bottom, cams[0], 0, "bottom", "sample"))
    plan += [Photo(ix.uniform, cams[c], c, "uniform", "sample") for c in range(len(cams))]
    if "bottom" in names:
        plan.append(Photo(ix.empty_bottom, cams[0], 0, "bottom", "empty"))
    return plan


def bracket_exposures(max_radiance: float, sensor) -> list[float]:
    """The exposure bracket of a photo whose brightest radiance is `max_radiance`: BRACKET exposures
    BRACKET_RATIO apart (twin.camera.hdr.choose_bracket) within EXPOSURE_LIMITS_S, in whole microseconds."""
    from twin.camera.hdr import choose_bracket

    ts = choose_bracket(max(max_radiance, 1e-12), sensor, n=BRACKET, ratio=BRACKET_RATIO)
    return [round(min(max(t, EXPOSURE_LIMITS_S[0]), EXPOSURE_LIMITS_S[1]) * EXPOSURE_STEPS_PER_S)
            / EXPOSURE_STEPS_PER_S for t in ts]


def exposure_frames(frames: int, exposures: int = BRACKET) -> list[int]:
    """How many times a photo takes each exposure of its ascending bracket: the shortest SHORTEST_REPEAT x `frames`
    times, the others `frames` times."""
    check_frames(frames)
    return [SHORTEST_REPEAT * frames] + [frames] * (exposures - 1)


def frames_per_photo(frames: int) -> int:
    """The raw frames a photo of the plan takes."""
    return sum(exposure_frames(frames))


def bracket_frames(exposures: list[float], frames: int) -> list[float]:
    """The exposures a photo's raw frames take, the ascending `exposures` each taken its `exposure_frames` times in a
    row (frame averaging: the photos' noise is what limits a weak lobe; docs/accuracy.md)."""
    return [t for t, n in zip(exposures, exposure_frames(frames, len(exposures))) for _ in range(n)]


def photo_exposures(max_radiance: float, sensor, frames: int = DEFAULT_FRAMES) -> list[float]:
    """The exposures of a photo's raw frames, in the order they are taken: the bracket of a photo whose brightest
    radiance is `max_radiance` (bracket_exposures), each exposure its `exposure_frames` times (bracket_frames)."""
    return bracket_frames(bracket_exposures(max_radiance, sensor), frames)


# `--frames`'s help, the same for every command that captures (twin.cli, hemicube.cli)
FRAMES_HELP = (f"frames taken of every exposure, the shortest {SHORTEST_REPEAT} times as many, averaged by the HDR "
               f"merge against the photos' noise (at most {MAX_FRAMES_PER_EXPOSURE}; default: %(default)s)")


def check_frames(frames) -> int:
    if not isinstance(frames, int) or isinstance(frames, bool) or not 1 <= frames <= MAX_FRAMES_PER_EXPOSURE:
        raise CaptureError(f"frames per exposure must be an integer in [1, {MAX_FRAMES_PER_EXPOSURE}] ({BRACKET} "
                           f"exposures a photo, the shortest {SHORTEST_REPEAT} times as often, {MAX_FRAMES_PER_PHOTO} "
                           f"frames at most), got {frames!r}")
    return frames


def frame_id(photo: Photo, j: int) -> int:
    """Counter for the sensor's random stream: unique per (photo, camera, exposure), not per run order."""
    return (photo.index * 8 + photo.camera_index) * 16 + j
