"""Reliability benchmarks of the hardware backend over the emulated devices (docs/reliability.md holds the
figures), each printed as JSON by `hemicube bench ...`:

    led-link        pattern uploads through the controller's emulator with one fault kind in turn on a share of
                    the frames, then random bit errors per byte: what was displayed (from the emulator's own
                    log), what damage got through (none may), retransmissions, timeouts, throughput
    resume          a mini-rig capture over the emulated devices SIGKILLed at random points and resumed each
                    time: it completes, no photo lost, doubled or mismatched, photos equal an uninterrupted run's
    camera-faults   a capture with failed buffers, disconnects and stray triggers injected into the cameras
    metering-faults the controller reset right after latching a pattern, before the photo's metering, until a
                    number of photos were hit: each retaken and equal to the simulator's, or refused by name

The captures compare against a simulator capture of the same rig, sample and seed, made once in the work
folder (`reference`).
"""
from __future__ import annotations

import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from twin import load_rig
from twin.capture.backends.faults import FAULT_KINDS
from twin.capture.plan import DEFAULT_SEED, DeviceError

SAMPLE, SEED, LEDS_MINI = "ramps", 1, 460
# the raw frames kept: the benchmarks compare every frame the devices delivered with the simulator's
CAPTURE_ARGS = ["capture", "--rig", "mini", "--sample", SAMPLE, "--seed", str(SEED), "--raw", "--no-progress"]
# the emulated controller's faults during the capture benchmarks: every kind, rarely
CAPTURE_LED_FAULTS = "corrupt=0.002,drop=0.002,dup=0.002,delay=0.002,reset=0.002,stuck=0.002,flip=1e-5,delay_s=0.3"


def _events(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines()]


def led_link_run(spec: str, uploads: int, leds: int, *, timeout_s: float, link: str, seed: int, log: Path) -> dict:
    """`uploads` random patterns shown through an emulator injecting `spec`; the figures of one run."""
    from twin.capture.backends.led_emulator import spawn
    from twin.capture.backends.led_host import LedController
    from twin.capture.backends.led_protocol import crc32

    proc, url = spawn(leds, link=link, faults=f"{spec},seed={seed}", log=log, seed=seed)
    rng = np.random.default_rng(seed)
    requested, failed, wrong_acks = [], 0, 0
    try:
        ctl = LedController(url, leds, timeout_s=timeout_s, backoff_s=timeout_s / 10, audit=True, seq0=seed)
        t0 = time.perf_counter()
        for _ in range(uploads):
            pattern = rng.integers(0, 256, (leds, 3), dtype=np.uint8)
            requested.append(f"{crc32(pattern.tobytes()):08x}")
            try:
                wrong_acks += ctl.show(pattern).displayed_crc != int(requested[-1], 16)
            except DeviceError:
                failed += 1
        wall = time.perf_counter() - t0
        ctl.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    events = _events(log)
    summary = events[-1]
    shown = [e["crc"] for e in events if e["event"] == "display"]
    shown_once = [c for i, c in enumerate(shown) if i == 0 or c != shown[i - 1]]  # again after a reset: one
    sent = bytes.fromhex(summary["sent_crcs"])
    sent = {int.from_bytes(sent[i:i + 4], "little") for i in range(0, len(sent), 4)}
    s = ctl.stats
    return {
        "faults": spec, "uploads": uploads, "pattern_bytes": 3 * leds, "link": link, "timeout_s": timeout_s,
        "faults_injected": summary["faults"],
        "uploads_failed": failed,  # a DeviceError after the retries: must be 0
        "acks_not_the_pattern": wrong_acks,
        "wrong_patterns_displayed": sum(c not in set(requested) for c in shown),
        "display_sequence_is_the_requested_one": shown_once == requested,
        "damaged_frames_to_device": summary["damaged_in"], "rejected_by_device": summary["rejected_in"],
        "damaged_frames_accepted_by_device": summary["damaged_in_accepted"],
        "damaged_replies_rejected_by_host": s.damaged_replies,
        "damaged_replies_accepted_by_host": len(set(s.accepted_crcs) - sent),
        "stalls_injected": sum(n for k, n in summary["faults"].items() if k.startswith(("delay", "stuck"))),
        "retransmissions": s.retransmissions, "timeouts": s.timeouts, "naks": s.naks,
        "stale_replies_ignored": s.stale_replies, "controller_resets_seen": s.reboots,
        "frames_sent": s.frames_sent, "wall_s": round(wall, 2), "uploads_per_s": round(uploads / wall, 1),
        "pattern_MB_per_s": round(uploads * 3 * leds / wall / 1e6, 2),
    }


def bench_led_link(uploads: int = 10_000, leds: int = 16_384, rate: float = 0.01, flip: float = 1e-5,
                   kinds=tuple(FAULT_KINDS), timeout_s: float = 0.03, delay_s: float = 0.06, link: str = "pty",
                   seed: int = DEFAULT_SEED, workdir=None) -> dict:
    workdir = Path(workdir or ".")
    workdir.mkdir(parents=True, exist_ok=True)
    specs = [f"{k}={rate},delay_s={delay_s}" for k in kinds] + ([f"flip={flip}"] if flip else [])
    link_url = "pty" if link == "pty" else "socket://127.0.0.1:0"
    runs = [led_link_run(spec, uploads, leds, timeout_s=timeout_s, link=link_url, seed=seed,
                         log=workdir / f"led_{spec.split('=')[0]}.jsonl") for spec in specs]
    return {"benchmark": "led-link", "runs": runs,
            "all_good": all(r["uploads_failed"] == r["wrong_patterns_displayed"] == r["acks_not_the_pattern"]
                            == r["damaged_frames_accepted_by_device"] == r["damaged_replies_accepted_by_host"] == 0
                            and r["display_sequence_is_the_requested_one"] for r in runs)}


def reference(workdir: Path) -> Path:
    """The simulator's capture that the hardware ones must equal (made once, resumed if need be)."""
    from twin.capture.runner import capture

    return capture(load_rig("mini"), SAMPLE, Path(workdir) / "sim", seed=SEED, progress=False, raw=True)


def check_capture(out: Path, ref: Path) -> dict:
    """What a finished hardware capture must show: complete, verified, equal to the reference, every photo
    acknowledged with its own pattern's CRC, no camera frame used twice."""
    from twin.capture.backends.led_protocol import crc32
    from twin.capture.session import LOCK, MANIFEST, CaptureSession

    hw, sim = CaptureSession.open(out), CaptureSession.open(ref)
    listed = set(hw.files) | {MANIFEST, LOCK}
    unlisted = [p for p in out.rglob("*") if p.is_file() and str(p.relative_to(out)) not in listed]
    patterns = hw.patterns()
    crc = {n: f"{crc32(patterns.levels[i].tobytes()):08x}" for i, n in enumerate(patterns.names)}
    frames, retakes = {}, {}
    for rec in hw.photos.values():
        frames.setdefault(rec["camera"], []).extend((rec["camera_run"], *f) for f in rec.get("camera_frames", []))
        for reason in rec.get("retakes", []):
            retakes[reason] = retakes.get(reason, 0) + 1
    photos = {f for rec in sim.photos.values() for f in rec["files"]}  # HDR photos, raw frames where ref kept them
    return {
        "photos": len(hw.photos), "photos_planned": len(hw.header["plan"]),
        "photos_lost": len(hw.header["plan"]) - len(hw.photos),
        "files_failing_checksum": len(hw.verify()), "files_not_in_the_manifest": len(unlisted),
        "photos_or_raw_frames_differing_from_the_simulator": sum(hw.files.get(k) != sim.files[k] for k in photos),
        "photos_acknowledged_with_another_pattern": sum(r["led_crc"] != crc[r["pattern"]] for r in hw.photos.values()),
        "camera_frames_used_twice": sum(len(v) - len(set(v)) for v in frames.values()),
        "brackets_retaken": retakes,
    }


def _photos(out: Path) -> int:
    """Photos a capture folder lists so far (0 before its manifest exists)."""
    from twin.capture.session import CaptureSession

    try:
        return len(CaptureSession.open(out).photos)
    except ValueError:  # not (yet) a capture folder, or a manifest being replaced
        return 0


def bench_resume(kills: int = 20, seed: int = DEFAULT_SEED, workdir=None) -> dict:
    """Kill points: `kills` photo counts drawn at random (seeded) over the plan; each run is SIGKILLed a random
    0-0.5 s after its manifest reaches the next count, or, when it already has, 0-15 s after it starts (in
    start-up, rendering, uploading)."""
    from twin.capture.backends.led_emulator import spawn

    workdir = Path(workdir or ".")
    ref = reference(workdir)
    rng = random.Random(seed)
    total = _photos(ref)
    targets = sorted(rng.randrange(total) for _ in range(kills))
    proc, url = spawn(LEDS_MINI, faults=f"{CAPTURE_LED_FAULTS},seed={seed}", log=workdir / "resume_led.jsonl")
    out = workdir / "resume"
    args = [sys.executable, "-m", "hemicube.cli", *CAPTURE_ARGS, "--backend", "hardware", "--led", url,
            "--cameras", "emulated", "-o", str(out)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    points, t_start = [], time.perf_counter()
    try:
        for target in targets:
            before = _photos(out)
            run = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            t0 = time.perf_counter()
            if before >= target:
                wait_until = t0 + rng.uniform(0, 15)
            else:
                while _photos(out) < target and run.poll() is None:
                    time.sleep(0.02)
                wait_until = time.perf_counter() + rng.uniform(0, 0.5)
            while time.perf_counter() < wait_until and run.poll() is None:
                time.sleep(0.01)
            finished = run.poll() is not None
            run.send_signal(signal.SIGKILL)
            run.wait()
            points.append({"photos_before": before, "target": target, "killed_after_s": round(time.perf_counter() - t0, 2),
                           "photos_at_kill": _photos(out), "had_finished": finished})
        final = subprocess.run(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    result = {"benchmark": "resume", "kills": points, "final_exit_code": final.returncode,
              "final_error": final.stderr.strip().splitlines()[-1:] if final.returncode else [],
              "wall_s": round(time.perf_counter() - t_start, 1)}
    if final.returncode == 0:
        result.update(check_capture(out, ref))
    return result


def bench_camera_faults(spec: str = "failed=0.02,disconnect=0.005,stray=0.02", seed: int = DEFAULT_SEED,
                        workdir=None) -> dict:
    from twin.capture.backends.faults import CameraFaults
    from twin.capture.backends.led_emulator import spawn
    from twin.capture.runner import capture

    workdir = Path(workdir or ".")
    ref = reference(workdir)
    faults = CameraFaults(f"{spec},seed={seed}")
    proc, url = spawn(LEDS_MINI)
    out = workdir / "camera_faults"
    t0 = time.perf_counter()
    try:
        capture(load_rig("mini"), SAMPLE, out, seed=SEED, backend="hardware", progress=False, raw=True,
                devices={"led": url, "cameras": "emulated", "camera_faults": faults})
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    return {"benchmark": "camera-faults", "faults": spec, "injected": faults.counts,
            "wall_s": round(time.perf_counter() - t0, 1), **check_capture(out, ref)}


def _new_events(log: Path, offset: int) -> tuple[list[dict], int]:
    """The emulator log's whole lines after byte `offset`, and the offset after them."""
    with open(log, "rb") as f:
        f.seek(offset)
        data = f.read()
    whole = data[:data.rfind(b"\n") + 1]
    return [json.loads(line) for line in whole.splitlines()], offset + len(whole)


def bench_metering_faults(injections: int = 100, rate: float = 0.25, seed: int = DEFAULT_SEED, workdir=None,
                          scale: float = 1.0) -> dict:
    """A controller reset during the metering, injected until `injections` photos were hit: the emulated
    controller browns out right after latching a pattern (`brownout=RATE`, twin.capture.backends.faults), so
    the host's next command, the photo's metering, finds the LEDs off. The mini plan's photos in turn (from its
    start again when it is done), each taken through the capture loop (twin.capture.runner.photos) over the
    emulated devices and compared, raw frames and HDR photo byte for byte, with the simulator's. A photo hit
    (one brownout or more while it was taken, from the emulator's log) is completed by retaking when it was
    retaken, kept and equals the simulator's; refused when the capture loop stopped at it by name. A photo not
    hit must be kept, equal, without a retake. `scale` resizes the cameras' images (0.5: a quarter of the rays to
    render, for a quick run)."""
    import hashlib

    from twin.capture.backends.led_emulator import spawn
    from twin.capture.plan import CaptureError, build_patterns, paper_plan
    from twin.capture.runner import SAMPLE_RESOLUTION, open_backends, photos, prepare
    from twin.materials.samples import load_sample

    def digest(raws, hdr) -> str:
        return hashlib.sha256(raws.numpy().tobytes() + hdr["radiance"].numpy().tobytes()).hexdigest()

    if not (0 < rate <= 1 and injections >= 1):  # else no photo would ever be hit: the run would not end
        raise CaptureError(f"metering-faults needs --rate in (0, 1] and --injections >= 1, got {rate} and "
                           f"{injections}")
    if not (math.isfinite(scale) and 0 < scale <= 1):  # checked before the work folder is made
        raise CaptureError(f"metering-faults needs --scale in (0, 1], got {scale}")
    workdir = Path(workdir or ".")
    workdir.mkdir(parents=True, exist_ok=True)
    rig = load_rig("mini")
    if scale != 1.0:
        rig = replace(rig, cameras={n: c.resized(scale) for n, c in rig.cameras.items()})
    maps = load_sample(SAMPLE, resolution=SAMPLE_RESOLUTION)
    patterns = build_patterns(rig)
    plan = paper_plan(rig, patterns)
    # camera by camera, the primary's photos of the sample first, their patterns rendered 64 at a time as they
    # come: a render evaluates the LEDs a group of patterns lights once for the group (all of them for the
    # learned patterns, a line's own for each line), so a short run renders the primary's learned ones only
    order = sorted(plan, key=lambda p: (p.sample != "sample", p.camera_index, p.index))
    faults = f"brownout={rate:g},seed={seed}"
    log = workdir / "metering_led.jsonl"
    log.unlink(missing_ok=True)
    proc, url = spawn(rig.num_leds, faults=faults, log=log)
    hit = {"photos": 0, "brownouts": 0, "completed_by_retaking": 0, "kept_without_a_retake": 0, "refused": 0}
    clean = {"photos": 0, "retaken": 0, "refused": 0}
    differing, retakes, refusals, reference, offset, taken, ready = 0, {}, [], {}, 0, 0, set()
    t0 = time.perf_counter()
    try:
        with open_backends(rig, maps, "hardware", SEED, "cpu", {"led": url, "cameras": "emulated"}) as hw:
            # the simulator's photos, from the twin that feeds the emulated cameras: one render of a pattern
            # serves both (a simulator backend of the same rig, sample and seed, as `--backend sim` opens)
            sim = {kind: backend.twin for kind, backend in hw.items()}
            while hit["photos"] < injections:
                at = taken % len(order)
                photo = order[at]
                taken += 1
                if at not in ready:
                    prepare(rig, hw, patterns, order[at:at + 64])
                    ready.update(range(at, at + 64))
                key = (photo.index, photo.camera_index)
                if key not in reference:
                    (_, raws, hdr, _), = photos(rig, sim, patterns, [photo], "cpu")
                    reference[key] = digest(raws, hdr)
                try:
                    (_, raws, hdr, record), = photos(rig, hw, patterns, [photo], "cpu")
                    kept, error = digest(raws, hdr), None
                except CaptureError as e:
                    kept, error, record = None, str(e), {}
                events, offset = _new_events(log, offset)
                brownouts = sum(e["event"] == "fault" and e["kind"] == "brownout" for e in events)
                for reason in record.get("retakes", []):
                    reason = re.sub(r"\d[\d.]*", "N", reason.split(" (")[0])  # without the CRC and figures
                    retakes[reason] = retakes.get(reason, 0) + 1
                differing += kept is not None and kept != reference[key]
                if error is not None:
                    refusals.append(error)
                if brownouts:
                    hit["photos"] += 1
                    hit["brownouts"] += brownouts
                    if error is not None:
                        hit["refused"] += 1
                    elif record.get("retakes"):
                        hit["completed_by_retaking"] += kept == reference[key]
                    else:
                        hit["kept_without_a_retake"] += 1
                else:
                    clean["photos"] += 1
                    clean["retaken"] += bool(record.get("retakes"))
                    clean["refused"] += error is not None
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    return {"benchmark": "metering-faults", "faults": faults, "camera_scale": scale, "photos": taken, "photos_hit": hit,
            "completed_by_retaking_share": round(hit["completed_by_retaking"] / max(hit["photos"], 1), 4),
            "photos_not_hit": clean, "accepted_photos_differing_from_the_simulator": differing,
            "retakes_by_reason": retakes, "refusals": refusals, "wall_s": round(time.perf_counter() - t0, 1)}
