"""A photo is kept only when it is plausible, judged from what a real capture has (twin.capture.plausibility):
metered under the pattern the LED controller acknowledged, its saturation and levels in agreement with its own
exposures; otherwise it is taken again, then refused by name. The controller reset before the metering is
injected by its emulator (its own process: `brownout`, a reset right after a latch), through the bench's tiny
mode; the 100-photo figure is in docs/reliability.md."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

import twin
from twin.capture.backends.sim import SimBackend
from twin.capture.plan import CaptureError, build_patterns, paper_plan, photo_exposures
from twin.capture.plausibility import MAX_SATURATED_SHARE, METER_ATTEMPTS, PHOTO_ATTEMPTS, judge_bracket
from twin.capture.runner import photos
from twin.materials.samples import load_sample
from twin.materials.suite import SUITE_SAMPLES

RIG = twin.load_rig("mini")
PATTERNS = build_patterns(RIG)
PLAN = paper_plan(RIG, PATTERNS)
UNIFORM = next(p for p in PLAN if p.pattern == "uniform" and p.camera_index == 0)


class DarkMetering:
    """The simulator `sim`, metering with the LEDs off its first `dark` times (no light: the radiance is linear in
    the LEDs' drive, Eq. 2), then lit: the photo a controller reset before the metering gave, its frames taken
    once the pattern was lit again."""

    def __init__(self, sim: SimBackend, dark: int):
        self.sim, self.dark = sim, dark

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def meter(self, camera: str) -> float:
        if self.dark == 0:
            return self.sim.meter(camera)
        self.dark -= 1
        return 0.0


@pytest.fixture(scope="module")
def sim():
    """The simulator showing the uniform light (rendered once for the module's tests)."""
    sim = SimBackend(RIG, load_sample("ramps", resolution=32), seed=1)
    sim.show(PATTERNS.levels[PATTERNS.names.index("uniform")])
    return sim


def _bracket(sim, exposures):
    import warp as wp

    cam = RIG.camera("primary")
    raws = wp.empty((len(exposures), cam.height, cam.width), dtype=wp.uint16, device="cpu")
    sim.grab_bracket("primary", exposures, list(range(len(exposures))), raws)
    return raws


def test_a_bracket_metered_in_the_dark_is_implausible(sim):
    """The photo of the report: metered with the LEDs off (1.0 s, the longest exposure, 16 times), taken lit."""
    sensor = RIG.camera("primary").sensor
    dark = photo_exposures(0.0, sensor)
    assert dark == [1.0] * 16
    j = judge_bracket(_bracket(sim, dark), dark, sensor)
    assert j.saturated_share > 0.9 and j.reason.startswith(f"{j.saturated_share:.1%} of its photosites saturated "
                                                           "in every frame (at most 1%; exposures 16 x 1 s)")
    good = photo_exposures(sim.meter("primary"), sensor)
    j = judge_bracket(_bracket(sim, good), good, sensor)
    assert j.reason is None and j.saturated_share <= MAX_SATURATED_SHARE
    assert abs(j.level_ratios[0] - 1) < 0.01  # the pair of the longest exposures: too few photosites unsaturated


def test_levels_that_disagree_with_the_exposures_are_implausible(sim):
    """A camera that applied other exposures than it reports: the levels of the bracket's second exposure are
    twice what the first one's and the reported exposures imply."""
    sensor = RIG.camera("primary").sensor
    taken = photo_exposures(sim.meter("primary"), sensor, frames=1)
    reported = [taken[0], taken[0], taken[2] / 2, taken[3] / 2]
    j = judge_bracket(_bracket(sim, taken), reported, sensor)
    assert j.level_ratios[0] == pytest.approx(2, rel=0.01)
    assert f"is {j.level_ratios[0]:.3g} x what its level at" in j.reason and j.reason.endswith("(within 10%)")


def test_an_implausible_photo_is_retaken_then_refused_by_name(sim):
    """In the capture loop: metered in the dark once, the photo is taken again and equals the simulator's; metered
    in the dark every time, the capture stops at it with one line naming it."""
    def take(dark):
        sims = {"sample": DarkMetering(sim, dark), "empty": None}
        (_, raws, _, record), = photos(RIG, sims, PATTERNS, [UNIFORM], "cpu")
        return raws.numpy(), record

    clean, record = take(0)
    assert "retakes" not in record
    retaken, record = take(1)
    assert np.array_equal(retaken, clean)
    assert len(record["retakes"]) == 1 and record["retakes"][0].startswith("implausible: ")
    assert "saturated in every frame" in record["retakes"][0]
    with pytest.raises(CaptureError) as e:
        take(PHOTO_ATTEMPTS)
    message = str(e.value)
    assert "\n" not in message
    assert message.startswith(f"photo img{UNIFORM.index:05d}_cam00 (uniform, camera primary) is implausible after "
                              f"{PHOTO_ATTEMPTS} takes: ")


# half the mini rig's image (111 x 96): the same photos, a quarter of the rays to render
HALF = replace(RIG, cameras={n: c.resized(0.5) for n, c in RIG.cameras.items()})


@pytest.mark.parametrize("name", SUITE_SAMPLES)
def test_clean_photos_of_every_suite_sample_are_plausible(name):
    """No retake, no refusal, on the photos of the primary camera that are brightest or darkest in their parts
    (uniform light, all bottom LEDs, the first and last line, a learned pair) of every suite sample; whole
    captures of every suite sample: docs/reliability.md."""
    lines = [p for p in PLAN if p.pattern.startswith("line_")]
    todo = [UNIFORM, lines[0], lines[-1], *[p for p in PLAN if p.camera_index == 0][:2]]
    todo += [p for p in PLAN if p.pattern == "bottom" and p.sample == "sample"]
    sims = {"sample": SimBackend(HALF, load_sample(name, resolution=32), seed=1), "empty": None}
    for photo, _, _, record in photos(HALF, sims, PATTERNS, todo, "cpu"):
        assert "retakes" not in record, (photo, record["retakes"])


def test_a_reset_before_the_metering_is_metered_again(tmp_path):
    """`hemicube bench metering-faults` in a tiny mode (half-size images): the emulated controller resets right
    after half its latches; every photo hit is metered again under the acknowledged pattern and kept equal to
    the simulator's, or refused by name when its meterings were all hit; the others are taken once."""
    from twin.capture.reliability import bench_metering_faults

    res = bench_metering_faults(injections=2, rate=0.5, seed=1, workdir=tmp_path, scale=0.5)
    hit = res["photos_hit"]
    assert hit["photos"] == 2 and hit["kept_without_a_retake"] == 0
    assert hit["completed_by_retaking"] >= 1 and hit["completed_by_retaking"] + hit["refused"] == 2
    assert all(e.startswith("photo img") and f"through the metering in {METER_ATTEMPTS} attempts" in e
               for e in res["refusals"]) and len(res["refusals"]) == hit["refused"]
    assert res["accepted_photos_differing_from_the_simulator"] == 0
    assert res["photos_not_hit"]["retaken"] == res["photos_not_hit"]["refused"] == 0
    assert set(res["retakes_by_reason"]) == {"the LEDs changed during the metering"}


def test_the_emulated_controller_browns_out_after_a_latch(tmp_path):
    """The injected fault, from the emulator's process: SHOW is acknowledged, then the controller restarts (new
    boot id, LEDs off) before the host's next command."""
    from twin.capture.backends.faults import FaultSpec
    from twin.capture.backends.led_emulator import spawn
    from twin.capture.backends.led_host import LedController
    from twin.capture.backends.led_protocol import crc32

    assert str(FaultSpec.parse("brownout=0.25,seed=2")) == "brownout=0.25,delay_s=0.5,seed=2"
    proc, url = spawn(RIG.num_leds, faults="brownout=1", log=tmp_path / "led.jsonl")
    try:
        with LedController(url, RIG.num_leds) as ctl:
            lit = PATTERNS.levels[PATTERNS.names.index("uniform")]
            ack = ctl.show(lit)
            assert ack.displayed_crc == crc32(lit.tobytes())
            now = ctl.query()
            assert now.boot_id != ack.boot_id and now.displayed_crc == crc32(bytes(lit.size))
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
    events = [e["event"] + e.get("kind", "") for e in map(json.loads, (tmp_path / "led.jsonl").read_text().splitlines())]
    assert events[events.index("display"):][:3] == ["display", "faultbrownout", "reset"]


def test_a_photo_never_metered_under_its_pattern_is_refused_by_name(tmp_path):
    """A controller that browns out after every latch: the photo is metered METER_ATTEMPTS times, never under the
    acknowledged pattern, and the capture stops at it with one line naming it."""
    from twin.capture.backends.led_emulator import spawn
    from twin.capture.backends.led_protocol import crc32
    from twin.capture.plan import DeviceError
    from twin.capture.runner import open_backends

    proc, url = spawn(RIG.num_leds, faults="brownout=1")
    try:
        with open_backends(HALF, load_sample("ramps", resolution=32), "hardware", 1, "cpu",
                           {"led": url, "cameras": "emulated"}) as hw:
            with pytest.raises(DeviceError) as e:
                list(photos(HALF, hw, PATTERNS, [UNIFORM], "cpu"))
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
    message = str(e.value)
    off = f"{crc32(bytes(RIG.num_leds * 3)):08x}"
    assert message == (f"photo img{UNIFORM.index:05d}_cam00: camera primary: the LEDs did not stay lit through the "
                       f"metering in {METER_ATTEMPTS} attempts ({METER_ATTEMPTS} x the LEDs changed during the metering "
                       f"(displayed {off}, the controller reset))")


@pytest.mark.parametrize("options", [{"rate": 0.0}, {"injections": 0}, {"scale": -1.0}, {"scale": float("nan")}])
def test_the_bench_refuses_bad_options_before_making_its_folder(tmp_path, options):
    """`hemicube bench metering-faults` with an option that could not run: one line naming it, no folder made."""
    from twin.capture.reliability import bench_metering_faults

    work = tmp_path / "work"
    with pytest.raises(CaptureError, match="metering-faults needs"):
        bench_metering_faults(**{"injections": 1, "rate": 0.5, "workdir": work, **options})
    assert not work.exists()
