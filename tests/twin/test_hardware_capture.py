"""`hemicube capture --backend hardware`: the same plan, session folder and resume as the simulator, through
the LED controller's emulator (its own process, faults injected) and pylon's camera emulation (faults
injected): the photos are byte-identical to `--backend sim`'s, their raw frames (kept with --raw) too, and a
damaged folder is resumed through the devices. (Resuming after SIGKILL at 20 random points: `hemicube bench resume`,
docs/reliability.md.)"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

import hemicube.cli
from twin.capture.backends.led_emulator import spawn
from twin.capture.backends.led_protocol import crc32
from twin.capture.plan import DEFAULT_FRAMES, frames_per_photo
from twin.capture.reliability import check_capture
from twin.capture.session import verify

ARGS = ["capture", "--rig", "mini", "--sample", "ramps", "--seed", "1", "--no-progress"]  # validate_dir's capture
LED_FAULTS = "corrupt=0.001,drop=0.001,dup=0.001,delay=0.001,reset=0.001,stuck=0.001,flip=1e-5,delay_s=0.3,seed=2"
CAMERA_FAULTS = "failed=0.01,disconnect=0.003,stray=0.01,seed=3"


def _manifest(d):
    return json.loads((Path(d) / "manifest.json").read_text())


@pytest.fixture(scope="module")
def controller(tmp_path_factory):
    log = tmp_path_factory.mktemp("emu") / "controller.jsonl"
    proc, url = spawn(460, faults=LED_FAULTS, log=log)
    yield url, log
    proc.terminate()
    proc.wait(10)


def test_hardware_capture_with_faults_equals_the_simulator_and_resumes(validate_dir, controller, tmp_path):
    url, log = controller
    out = tmp_path / "hw"
    args = ARGS + ["--backend", "hardware", "--led", url, "--cameras", "emulated", "--camera-faults", CAMERA_FAULTS,
                   "--raw", "-o", str(out)]
    assert hemicube.cli.main(args) == 0
    hw, sim = _manifest(out), _manifest(validate_dir / "capture")  # the simulator's, without raw frames
    raws = {rel for rel in hw["files"] if rel.startswith("raw/")}
    n = frames_per_photo(DEFAULT_FRAMES)  # raw frames a photo
    # byte-identical photos, merged from the raw frames, patterns, rig and ground truth
    assert len(raws) == 196 * n and {k: v for k, v in hw["files"].items() if k not in raws} == sim["files"]
    report = check_capture(out, validate_dir / "capture")
    assert {k: v for k, v in report.items() if k != "brackets_retaken"} == {
        "photos": 196, "photos_planned": 196, "photos_lost": 0, "files_failing_checksum": 0,
        "files_not_in_the_manifest": 0,
        "photos_or_raw_frames_differing_from_the_simulator": 0, "photos_acknowledged_with_another_pattern": 0,
        "camera_frames_used_twice": 0}
    assert report["brackets_retaken"]  # the camera faults cost retakes
    assert all(len(rec["camera_frames"]) == n for rec in hw["photos"].values())
    assert sum(json.loads(line)["event"] == "fault" for line in log.read_text().splitlines()) > 0
    _raw_frames_are_the_simulators(out, ["img00003_cam01", "img00129_cam00"])

    # resume: a damaged photo and a lost raw frame (of the secondary camera: its 64 patterns are rendered again,
    # as a batch) are taken again through the devices, byte for byte, nothing else
    (out / "img00060_cam01.exr").write_bytes(b"damaged")
    (out / "raw" / "img00003_cam01_e1.BayerRG12p").unlink()
    mtimes = {rel: (out / rel).stat().st_mtime_ns for rel in hw["files"] if (out / rel).exists()}
    assert hemicube.cli.main(args) == 0
    assert verify(out) == [] and _manifest(out)["files"] == hw["files"]
    redone = {rel for rel in mtimes if (out / rel).stat().st_mtime_ns != mtimes[rel]}
    assert {r for r in redone if r.startswith(("img", "raw/"))} == {
        "img00060_cam01.exr", *(f"raw/img00060_cam01_e{j}.BayerRG12p" for j in range(n)),
        "img00003_cam01.exr", *(f"raw/img00003_cam01_e{j}.BayerRG12p" for j in range(n) if j != 1)}


def _raw_frames_are_the_simulators(out: Path, stems: list[str]) -> None:
    """The raw frames of these photos of the capture in `out` are those the simulator takes of them (here, in this
    process: the folder it is compared with keeps none)."""
    import numpy as np

    import twin
    from twin.capture.runner import SAMPLE_RESOLUTION, capture_header, open_backends, photos
    from twin.capture.session import CaptureSession, photo_stem
    from twin.materials.samples import load_sample

    rig, session = twin.load_rig("mini"), CaptureSession.open(out)
    _, patterns, plan = capture_header(rig, "ramps", seed=1)
    todo = [p for p in plan if photo_stem(p.index, p.camera_index) in stems]
    with open_backends(rig, load_sample("ramps", resolution=SAMPLE_RESOLUTION), "sim", 1, "cpu") as sims:
        for photo, raws, _, _ in photos(rig, sims, patterns, todo, "cpu"):
            kept = session.raw_frames(photo.index, photo.camera_index)
            assert len(kept) == raws.shape[0] and all(np.array_equal(a, b) for a, b in zip(kept, raws.numpy()))
    assert len(todo) == len(stems)


def test_hardware_capture_errors(controller, tmp_path, capsys):
    url, _ = controller
    base = ARGS + ["--backend", "hardware"]
    for extra, message in [([], "needs --led"), (["--led", url], "needs --cameras"),
                           (["--led", "socket://127.0.0.1:9", "--cameras", "emulated"], "cannot open the link"),
                           (["--led", url, "--cameras", "basler"], "no a2A5328-15ucPRO whose DeviceUserID"),
                           (["--led", url, "--cameras", "basler", "--camera-faults", "failed=0.1"], "emulated cameras only")]:
        out = tmp_path / "x"
        assert hemicube.cli.main(base + extra + ["-o", str(out)]) == 2
        assert message in capsys.readouterr().err
        assert not out.exists()  # nothing is made before the devices are open
    assert hemicube.cli.main(ARGS + ["--led", url, "-o", str(tmp_path / "y")]) == 2
    assert "options of --backend hardware" in capsys.readouterr().err


def test_frames_of_a_pattern_other_than_the_acknowledged_one_are_never_kept():
    """The emulated cameras see what the controller says it displays; when that is not the pattern the photo
    acknowledged (here another pattern is lit behind the backend's back), the bracket is refused, the
    pattern lit again and the bracket retaken: the frame kept is the right pattern's, as the simulator's."""
    import warp as wp

    import twin
    from twin.capture.patterns import PatternSet
    from twin.capture.plan import build_patterns
    from twin.capture.runner import open_backends
    from twin.materials.samples import load_sample

    rig = twin.load_rig("mini")
    maps = load_sample("ramps", resolution=32)
    ps = build_patterns(rig)
    two = PatternSet(ps.levels[[0, 64]], (ps.names[0], ps.names[64]), rig.name)
    proc, url = spawn(460)
    try:
        frames = {}
        for name, devices in (("sim", None), ("hardware", {"led": url, "cameras": "emulated"})):
            with open_backends(rig, maps, name, 1, "cpu", devices) as b:
                be = b["sample"]
                be.prepare("primary", two)
                be.show(two.levels[0])
                if name == "hardware":
                    be.devices.led.show(two.levels[1])  # someone else lights the line
                out = wp.empty((1, 192, 222), dtype=wp.uint16, device="cpu")
                _, record = be.grab_bracket("primary", [1e-3], [7], out)
                frames[name] = out.numpy()
        assert record["retakes"] == [f"the LEDs changed during the bracket (displayed "
                                     f"{crc32(two.levels[1].tobytes()):08x})"]
        assert (frames["hardware"] == frames["sim"]).all()
    finally:
        proc.terminate()
        proc.wait(10)
