"""`hemicube controller serve`: the LED controller's firmware, emulated in its own process, speaking the
protocol of docs/led-protocol.md from the device side on a TCP port or a pty, with faults injected on
request.

`Firmware` is the device logic alone (slots, the display, answering a retransmission without executing it
twice); it is the reference a firmware writer can read beside the specification. `Faults` damages frames
in either direction as `--faults` asks (grammar in `FaultSpec.parse` and the doc). `serve` runs the link:
one host at a time, the controller's state kept across host connections (a real controller stays powered
when the host's port closes), until SIGTERM/SIGINT. A TCP link listens on loopback unless `--allow-remote`
says otherwise, which needs a token that every host must prove it holds (led_auth); a host that sends
nothing for `--idle-timeout` seconds is disconnected, so that it cannot keep the others out.

With `--log FILE` every injected fault, every pattern latched onto the LEDs and every reset is written as a
JSON line, and at exit a summary with the counters and the CRCs of every frame the device sent undamaged,
so that a benchmark can check, from the device's side, what was displayed and what got through.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import random
import select
import signal
import socket
import subprocess
import sys
import time
from collections import deque

from twin.capture.backends import led_auth
from twin.capture.backends.led_link import admitted, open_link, pump
from twin.capture.backends.led_protocol import (LIST_ENTRY, MAX_CHUNK, MAX_PAYLOAD, MAX_WIRE, NAK, NO_SLOT, READ_ARGS,
                                                REPLY, SLOT_CRC, STATE, VERSION, WRITE_HEAD, Cmd, DeviceInfo, Frame,
                                                FrameError, FrameReader, SlotFlag, State, Status, cobs_decode,
                                                crc32, encode_frame)
from twin.capture.backends.faults import FAULT_KINDS, Faults, FaultSpec
from twin.capture.plan import DEFAULT_SEED, CaptureError
from twin.exitcodes import EXIT_IO, EXIT_USAGE

FIRMWARE_NAME = "hemicube-twin emulator"
MAX_SLOTS = (MAX_PAYLOAD - STATE.size) // LIST_ENTRY.size  # what one LIST reply can describe (817)
IDLE_TIMEOUT_S = 30.0
RECV = 65536  # bytes read from the link at a time


class Firmware:
    """The controller's state machine. `handle(item)` takes a decoded Frame (or the FrameError of one that
    failed its checks) and returns the reply's wire bytes, or None when there is nothing to answer."""

    def __init__(self, num_leds: int, slots: int, seed: int = 0, on_display=None):
        if not 0 < num_leds <= 0xFFFF:
            raise CaptureError(f"LED count {num_leds} out of range 1..65535 (HELLO carries it as u16)")
        if not 1 <= slots <= MAX_SLOTS:
            raise CaptureError(f"slots must be 1..{MAX_SLOTS} (one LIST reply describes them all), got {slots}")
        self.num_leds, self.size, self.num_slots = num_leds, 3 * num_leds, slots
        self._rng = random.Random(seed)  # boot ids: different after every reset, the same for a given seed
        self._on_display = on_display or (lambda state, data: None)
        self.latches = 0  # patterns latched onto the LEDs since power-on, resets included (a fault's trigger)
        self.boot()

    def boot(self) -> None:
        """Power-on state: every slot empty (zeros), the LEDs off, the counters and the reply cache cleared."""
        self.boot_id = self._rng.getrandbits(32)
        self.slots: list[bytearray | None] = [None] * self.num_slots  # None: all zeros, allocated on write
        self.flags = [SlotFlag.EMPTY] * self.num_slots
        self.crcs = [0] * self.num_slots
        self.display = bytes(self.size)
        self.displayed_slot, self.displayed_crc = NO_SLOT, crc32(self.display)
        self.rejected = 0
        self._last: tuple[int, int, bytes] | None = None  # (seq, frame CRC, reply) of the last command

    def state(self, status: int) -> bytes:
        return State(status, self.boot_id, self.displayed_slot, self.displayed_crc, self.rejected).pack()

    def handle(self, item) -> bytes | None:
        if isinstance(item, FrameError):
            self.rejected += 1
            if item.seq is None:
                return None  # not even a header to answer to
            return encode_frame(NAK, item.seq, self.state(Status.FRAME if item.version_ok else Status.VERSION))
        if self._last is not None and self._last[:2] == (item.seq, item.crc):
            return self._last[2]  # the host's retransmission of the last command: answer, do not redo
        status, extra = self._execute(item)
        known = item.type in Cmd._value2member_map_
        reply = encode_frame(item.type | REPLY if known else NAK, item.seq, self.state(status) + extra)
        self._last = (item.seq, item.crc, reply)
        return reply

    def _slot(self, slot: int) -> bool:
        return 0 <= slot < self.num_slots

    def _execute(self, f: Frame) -> tuple[int, bytes]:
        p = f.payload
        if f.type in (Cmd.HELLO, Cmd.STATE, Cmd.LIST, Cmd.RESET) and p:
            return Status.LENGTH, b""
        if f.type == Cmd.HELLO:
            return Status.OK, DeviceInfo(VERSION, 3, self.num_leds, self.num_slots, MAX_PAYLOAD,
                                         FIRMWARE_NAME).pack()
        if f.type == Cmd.STATE:
            return Status.OK, b""
        if f.type == Cmd.RESET:
            self.boot()
            return Status.OK, b""
        if f.type == Cmd.LIST:
            return Status.OK, b"".join(LIST_ENTRY.pack(fl, c) for fl, c in zip(self.flags, self.crcs))
        if f.type == Cmd.WRITE:
            if len(p) < WRITE_HEAD.size or len(p) > WRITE_HEAD.size + MAX_CHUNK:
                return Status.LENGTH, b""
            slot, off = WRITE_HEAD.unpack_from(p)
            data = p[WRITE_HEAD.size:]
            if not self._slot(slot):
                return Status.SLOT, b""
            if off + len(data) > self.size:
                return Status.RANGE, b""
            if self.slots[slot] is None:
                self.slots[slot] = bytearray(self.size)
            self.slots[slot][off:off + len(data)] = data
            self.flags[slot] = SlotFlag.DIRTY
            return Status.OK, b""
        if f.type in (Cmd.COMMIT, Cmd.SHOW):
            if len(p) != SLOT_CRC.size:
                return Status.LENGTH, b""
            slot, crc = SLOT_CRC.unpack(p)
            if not self._slot(slot):
                return Status.SLOT, b""
            if f.type == Cmd.COMMIT:
                actual = crc32(self.slots[slot] if self.slots[slot] is not None else bytes(self.size))
                if actual != crc:
                    return Status.MISMATCH, actual.to_bytes(4, "little")
                self.flags[slot], self.crcs[slot] = SlotFlag.VALID, actual
                return Status.OK, actual.to_bytes(4, "little")
            if self.flags[slot] != SlotFlag.VALID:
                return Status.SLOT, b""
            if self.crcs[slot] != crc:
                return Status.MISMATCH, b""
            # latch: the display buffer is separate from the slots, so later WRITEs never touch lit LEDs;
            # its CRC is computed from the display buffer itself, i.e. from what is lit
            self.display = bytes(self.slots[slot] if self.slots[slot] is not None else bytes(self.size))
            self.displayed_slot, self.displayed_crc = slot, crc32(self.display)
            self.latches += 1
            self._on_display(self, self.display)
            return Status.OK, b""
        if f.type == Cmd.READ:
            if len(p) != READ_ARGS.size:
                return Status.LENGTH, b""
            slot, off, n = READ_ARGS.unpack(p)
            if slot != NO_SLOT and not self._slot(slot):
                return Status.SLOT, b""
            if n > MAX_CHUNK or off + n > self.size:
                return Status.RANGE, b""
            src = self.display if slot == NO_SLOT else (self.slots[slot] or bytes(self.size))
            return Status.OK, bytes(src[off:off + n])
        return Status.UNKNOWN, b""


class Device:
    """The firmware behind a fault injector: bytes in from the link, bytes out to it."""

    def __init__(self, firmware: Firmware, faults: Faults, log):
        self.fw, self.faults, self.log = firmware, faults, log
        self._split = bytearray()  # incoming bytes not yet ending in a delimiter
        self._reader = FrameReader()
        self._clean = deque(maxlen=4)  # recent undamaged incoming frames, to judge what damage got through
        self._last_out: bytes | None = None
        self.sent_crcs: list[int] = []
        self.damaged_in = self.rejected_in = self.damaged_in_accepted = 0

    def receive(self, data: bytes, send) -> None:
        self._split += data
        while (end := self._split.find(0)) >= 0:
            wire = bytes(self._split[:end + 1])
            del self._split[:end + 1]
            if self._reader.dropping:  # the end of an over-long run, already dropped
                self._reader.feed(wire)
            else:
                self._frame_in(wire, send)
        if len(self._split) > MAX_WIRE:
            # longer than any frame: dropped as it arrives (counted once, as a bad frame without a header, which
            # gets no reply), so that memory stays bounded however long the run without a delimiter
            for item in self._reader.feed(bytes(self._split)):
                self.fw.handle(item)
            self._split.clear()

    def _frame_in(self, wire: bytes, send) -> None:
        self._clean.extend(f for f in FrameReader().feed(wire) if isinstance(f, Frame))
        kind = self.faults.pick("in") if len(wire) > 1 else None
        if kind:
            self.log.write({"event": "fault", "kind": kind, "dir": "in"})
        if kind == "delay":
            time.sleep(self.faults.spec.delay_s)
        if kind == "reset":  # part of the frame arrives, then the controller restarts and loses the rest
            self.fw.boot()
            self._reader = FrameReader()
            self.log.write({"event": "reset", "boot_id": self.fw.boot_id})
            return
        if kind in ("drop", "corrupt"):
            wire = self.faults.damage(wire, kind)
        wire, flipped = self.faults.flips(wire, "in")
        self.damaged_in += kind in ("drop", "corrupt") or flipped > 0
        latches = self.fw.latches
        for _ in range(2 if kind == "dup" else 1):
            for item in self._reader.feed(wire):
                self._judge(item)
                reply = self.fw.handle(item)
                if reply is not None:
                    self._send(reply, send)
        if self.fw.latches > latches and self.faults.brownout():  # acknowledged, then the supply dips
            self.log.write({"event": "fault", "kind": "brownout", "dir": "in"})
            self.fw.boot()
            self.log.write({"event": "reset", "boot_id": self.fw.boot_id})

    def _judge(self, item) -> None:
        """Damaged incoming frames must fail their checks: count those that did, and any frame that decoded
        but is not one the host sent (a CRC-32 miss)."""
        if isinstance(item, FrameError):
            self.rejected_in += 1
        elif item not in self._clean:
            self.damaged_in_accepted += 1
            self.log.write({"event": "damaged_frame_accepted", "seq": item.seq})

    def _send(self, reply: bytes, send) -> None:
        kind = self.faults.pick("out")
        previous, self._last_out = self._last_out, reply
        self.sent_crcs.append(int.from_bytes(cobs_decode(reply[:-1])[-4:], "little"))
        if kind:
            self.log.write({"event": "fault", "kind": kind, "dir": "out"})
        if kind == "stuck":
            if previous is None:
                return
            reply = previous
        elif kind == "delay":
            time.sleep(self.faults.spec.delay_s)
        elif kind in ("drop", "corrupt"):
            reply = self.faults.damage(reply, kind)
        reply, _ = self.faults.flips(reply, "out")
        send(reply * (2 if kind == "dup" else 1))


class EventLog:
    def __init__(self, path):
        try:
            self._f = open(path, "a", buffering=1) if path else None
        except (IsADirectoryError, NotADirectoryError, FileNotFoundError) as e:  # names no file one may make: input
            raise CaptureError(f"--log {path}: {e.strerror}") from None
        except OSError as e:  # the system refuses the write (permissions, a read-only place): exit 3, not 2
            raise OSError(e.errno, e.strerror, f"--log {path}") from None

    def write(self, event: dict) -> None:
        if self._f is not None:
            self._f.write(json.dumps(event, separators=(",", ":")) + "\n")

    def close(self) -> None:
        if self._f is not None:
            self._f.close()


def serve(link: str, num_leds: int, *, slots: int = 256, faults: str | None = None, seed: int = DEFAULT_SEED,
          log_path=None, allow_remote: bool = False, token_file=None, idle_timeout_s: float = IDLE_TIMEOUT_S,
          out=sys.stdout) -> None:
    """Serve until SIGTERM/SIGINT. Prints `serving URL (...)` on one line first; every error before that is a
    CaptureError of one line (bad input), or an OSError whose filename says what the system refused (the --log file),
    with nothing left listening or written."""
    spec = FaultSpec.parse(faults)
    if not (math.isfinite(idle_timeout_s) and idle_timeout_s > 0):
        raise CaptureError(f"--idle-timeout must be a positive number of seconds, got {idle_timeout_s}")
    if link == "pty" and (token_file is not None or allow_remote):
        raise CaptureError("--token-file and --allow-remote are for TCP links: a pty is reached from this machine only")
    token = led_auth.load_token(token_file) if link != "pty" else None
    log = None

    def displayed(fw, data):
        log.write({"event": "display", "slot": fw.displayed_slot, "crc": f"{fw.displayed_crc:08x}",
                   "sha256": hashlib.sha256(data).hexdigest()[:16]})

    firmware = Firmware(num_leds, slots, seed=seed, on_display=displayed)
    url, srv, master, slave = open_link(link, allow_remote, token)
    try:
        log = EventLog(log_path)
        device = Device(firmware, Faults(spec), log)

        def stop(signum, frame):
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, stop)
        access = "; token required" if token is not None else ""
        print(f"serving {url} ({num_leds} LEDs, {slots} slots; faults: {spec}{access})", file=out, flush=True)
        log.write({"event": "listen", "url": url})
        if master is not None:
            pump(master, device.receive, lambda b: os.write(master, b), lambda: os.read(master, RECV))
        else:
            while True:
                conn, peer = srv.accept()
                with conn:
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    log.write({"event": "connect", "peer": peer[0]})
                    if token is not None and not admitted(conn, token, min(led_auth.TIMEOUT_S, idle_timeout_s)):
                        log.write({"event": "refused", "peer": peer[0]})
                        continue
                    why = pump(conn, device.receive, conn.sendall, lambda: conn.recv(RECV), idle_timeout_s)
                log.write({"event": "disconnect", "reason": why})
    except KeyboardInterrupt:
        pass
    finally:
        if log is not None:
            log.write({"event": "summary", "faults": device.faults.counts, "rejected_in": device.rejected_in,
                       "damaged_in": device.damaged_in, "damaged_in_accepted": device.damaged_in_accepted,
                       "sent": len(device.sent_crcs), "sent_crcs": b"".join(
                           c.to_bytes(4, "little") for c in device.sent_crcs).hex()})
            log.close()
        for fd in (master, slave):
            if fd is not None:
                os.close(fd)
        if srv is not None:
            srv.close()


def add_arguments(p) -> None:
    """`hemicube controller serve`'s options (also `python -m twin.capture.backends.led_emulator`)."""
    p.add_argument("--link", required=True, help="socket://127.0.0.1:PORT (TCP on loopback; port 0 picks a free "
                   "one; another address needs --allow-remote) or pty (a pseudo-terminal whose path is printed)")
    p.add_argument("--allow-remote", action="store_true", help="let --link listen where other hosts can reach it "
                   "(socket://0.0.0.0:PORT, a LAN address): only with a token")
    p.add_argument("--token-file", help="file whose first line is the token (16+ characters) every TCP host must "
                   f"prove it holds before its first frame (docs/led-protocol.md, 1.1; default: ${led_auth.TOKEN_ENV}, "
                   "if set; the hosts read it from there); never printed or logged")
    p.add_argument("--idle-timeout", type=float, default=IDLE_TIMEOUT_S, metavar="S", help="disconnect a TCP host "
                   "that sends nothing for S seconds, so that another can connect; the host reconnects by itself "
                   "(default: %(default)s)")
    p.add_argument("--rig", default="mini", help="built-in rig or rig folder whose LED count the controller drives "
                   "(default: %(default)s)")
    p.add_argument("--leds", type=int, help="LED count, instead of --rig's")
    p.add_argument("--slots", type=int, default=256, help="pattern slots in the controller's memory "
                   "(default: %(default)s)")
    p.add_argument("--faults", help="faults to inject, e.g. corrupt=0.01,delay=0.01,flip=1e-5,seed=3 (kinds: "
                   + ", ".join(FAULT_KINDS) + "; brownout=P: a reset right after latching a pattern; "
                   "docs/led-protocol.md)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the controller's boot ids "
                   "(default: %(default)s)")
    p.add_argument("--log", help="append JSON lines here: faults injected, patterns displayed, resets, a summary "
                   "at exit")


def run(args) -> int:
    if args.leds is None:
        import twin

        args.leds = twin.load_rig(args.rig).num_leds
    serve(args.link, args.leds, slots=args.slots, faults=args.faults, seed=args.seed, log_path=args.log,
          allow_remote=args.allow_remote, token_file=args.token_file, idle_timeout_s=args.idle_timeout)
    return 0


def spawn(num_leds: int, *, link: str = "socket://127.0.0.1:0", faults: str | None = None, slots: int = 256,
          seed: int = DEFAULT_SEED, log=None, token: str | None = None, allow_remote: bool = False,
          idle_timeout_s: float | None = None, timeout_s: float = 60.0) -> tuple[subprocess.Popen, str]:
    """Start the emulator as its own process; returns it and the URL it serves (terminate it when done). A
    `token` goes to it in its environment, never on its command line, which every user of the machine can read."""
    cmd = [sys.executable, "-m", "twin.capture.backends.led_emulator", "--link", link, "--leds", str(num_leds),
           "--slots", str(slots), "--seed", str(seed)]
    cmd += ["--faults", faults] if faults else []
    cmd += ["--log", str(log)] if log else []
    cmd += ["--allow-remote"] if allow_remote else []
    cmd += ["--idle-timeout", str(idle_timeout_s)] if idle_timeout_s is not None else []
    env = {**os.environ, led_auth.TOKEN_ENV: token} if token is not None else None
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    line = proc.stdout.readline() if ready else ""
    if not line.startswith("serving "):
        proc.kill()
        raise CaptureError(f"the LED controller emulator did not start: {line.strip() or proc.stderr.read().strip()}")
    return proc, line.split()[1]


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m twin.capture.backends.led_emulator", description=__doc__.split("\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except ValueError as e:
        print(f"led_emulator: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:  # the system's refusal (twin.exitcodes): one line, as hemicube's own
        where = f"{os.fsdecode(e.filename)}: " if e.filename is not None else ""
        print(f"led_emulator: error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_IO


if __name__ == "__main__":
    sys.exit(main())
