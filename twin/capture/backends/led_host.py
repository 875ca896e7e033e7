"""The host side of the LED controller protocol (docs/led-protocol.md), over any pyserial URL: a real port
(/dev/ttyACM0), a pty, socket://HOST:PORT (the emulator) or loop://.

`LedController.show(levels)` is what the capture needs: it makes sure the pattern sits in a slot of the
controller (uploading it, or only the runs that differ from what the chosen slot holds), latches it, and
returns the controller's state, whose `displayed_crc` is the CRC-32 of what the LEDs show; it raises
DeviceError unless that equals the pattern's CRC. Every command is stop-and-wait: sent, then retransmitted
with the same sequence number after a timeout, a damaged reply or a NAK, with exponential backoff, until
`retries` retransmissions have failed, which raises one DeviceError that says what went wrong.

On a socket:// link to a controller that asks for a token (`hemicube controller serve` with one), the host
proves it holds the same token before its first frame (led_auth; the token from $HEMICUBE_LED_TOKEN), on
every connection, reconnections included.
"""
from __future__ import annotations

import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from twin.capture.backends import led_auth
from twin.capture.backends.led_protocol import (LIST_ENTRY, MAX_CHUNK, MAX_PAYLOAD, NAK, READ_ARGS, REPLY,
                                                SLOT_CRC, STATE, Cmd, DeviceInfo, Frame, FrameError, FrameReader,
                                                SlotFlag, State, Status, changed_runs, crc32, encode_frame,
                                                write_chunks)
from twin.capture.plan import DeviceError

try:
    import serial
except ImportError:  # pragma: no cover - depends on the install
    serial = None

DEFAULT_BAUD = 2_000_000  # a UART bridge's nominal rate; USB CDC and sockets ignore it (timeouts use it)
POLL_S = 0.01  # longest single blocking read: bounds how late a deadline is noticed
REPLY_MAX = 64  # bytes on the wire of every reply but LIST/READ/HELLO (used for timeouts only)


@dataclass
class LinkStats:
    commands: int = 0
    frames_sent: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    retransmissions: int = 0
    timeouts: int = 0
    damaged_replies: int = 0   # reply frames that failed COBS/length/CRC checks
    naks: int = 0              # the controller rejected our frame (damaged on its way there)
    stale_replies: int = 0     # well-formed replies to an earlier sequence number (late or duplicated)
    reboots: int = 0           # the controller's boot id changed under us
    reconnects: int = 0
    uploads: int = 0
    pattern_bytes_written: int = 0
    accepted_crcs: list = field(default_factory=list)  # CRC field of every reply accepted (audit only)


class _Rebooted(Exception):
    """The controller reset while an operation was under way: its slots are empty again."""


class LedController:
    def __init__(self, url: str, num_leds: int | None = None, *, baudrate: int = DEFAULT_BAUD,
                 timeout_s: float = 0.2, retries: int = 8, backoff_s: float = 0.01, seq0: int = 0,
                 audit: bool = False, token: bytes | None = None):
        if serial is None:
            raise DeviceError("the LED controller link needs pyserial: pip install 'hemicube-twin[hardware]'")
        self.url, self.baudrate = url, baudrate
        self.timeout_s, self.retries, self.backoff_s = timeout_s, retries, backoff_s
        self.stats = LinkStats()
        self._audit = audit
        self._token = token if token is not None else led_auth.load_token()
        self._seq = seq0 & 0xFFFF
        self._port = None
        self._open()
        self.boot_id: int | None = None
        self.info = DeviceInfo.unpack(self._command(Cmd.HELLO)[1])
        if num_leds is not None and self.info.num_leds != num_leds:
            self.close()
            raise DeviceError(f"LED controller at {url} drives {self.info.num_leds} LEDs; the rig has {num_leds}")
        if self.info.max_payload < MAX_PAYLOAD or self.info.bytes_per_led != 3:
            self.close()
            raise DeviceError(f"LED controller at {url}: unsupported device ({self.info})")
        self.size = 3 * self.info.num_leds
        self._patterns: dict[int, bytes] = {}  # crc -> bytes of every pattern this host has shown
        self._sync()

    # --- the link -------------------------------------------------------------------------------------
    def _open(self) -> None:
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=POLL_S,
                                               write_timeout=max(1.0, 20 * MAX_PAYLOAD / self._rate()))
        except (serial.SerialException, ValueError, OSError) as e:
            raise DeviceError(f"LED controller at {self.url}: cannot open the link ({e})") from None
        tcp = self.url.startswith("socket://")
        if tcp and self._token is not None:
            self._authenticate()
        self._port.reset_input_buffer()  # replies meant for an earlier host
        self._reader = FrameReader()
        self._pending: deque = deque()  # frames read but not yet looked at
        self._head = bytearray() if tcp and self._token is None else None  # this link's first bytes (_spot_handshake)

    def _authenticate(self) -> None:
        """The token handshake (led_auth), before the first frame: each end proves it holds the token."""
        def read_some(_left: float) -> bytes:
            return self._port.read_until(b"\n", led_auth.LINE_MAX + 1)  # returns within POLL_S

        deadline = time.monotonic() + led_auth.TIMEOUT_S
        try:
            led_auth.host(self._token, self._port.write, lambda: led_auth.read_line(read_some, deadline))
        except (led_auth.HandshakeError, serial.SerialException, OSError) as e:
            self._port.close()  # closed, not dropped: a retry after a failed reconnection reopens it
            raise DeviceError(f"LED controller at {self.url}: the token handshake failed: {e} (this host's token is "
                              f"{led_auth.TOKEN_ENV}'s; the controller must be serving with the same one)") from None

    def _spot_handshake(self, data: bytes) -> None:
        """A controller that asks for a token answers a host that sent a frame instead with a handshake line,
        then closes the link: say so, rather than retry a link that will never carry a frame."""
        self._head += data
        if self._head.startswith(led_auth.MAGIC):
            self._port.close()
            raise DeviceError(f"LED controller at {self.url} asks for a token: set {led_auth.TOKEN_ENV} to the "
                              "token it was started with")
        if not led_auth.MAGIC.startswith(bytes(self._head)):
            self._head = None

    def _reopen(self) -> None:
        self.stats.reconnects += 1
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass
        self._open()

    def close(self) -> None:
        if self._port is not None:
            self._port.close()
            self._port = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def _rate(self) -> float:
        return self.baudrate / 10.0  # bytes per second: 8N1 is 10 bits per byte

    def _send(self, wire: bytes) -> None:
        # the leading delimiter ends any partial frame the controller holds (resynchronisation)
        self._port.write(b"\x00" + wire)
        self.stats.frames_sent += 1
        self.stats.bytes_sent += len(wire) + 1

    def _await(self, seq: int, cmd: int, deadline: float):
        """The reply to (seq, cmd), or the reason to retransmit: 'timeout', 'damaged' or 'nak'."""
        while True:
            while self._pending:
                item = self._pending.popleft()
                if isinstance(item, FrameError):
                    self.stats.damaged_replies += 1
                    return "damaged"  # probably our reply: ask again now rather than wait
                if item.seq != seq or item.type not in (cmd | REPLY, NAK):
                    self.stats.stale_replies += 1
                    continue
                state = State.unpack(item.payload)
                if item.type == NAK:
                    if state.status == Status.VERSION:
                        raise DeviceError(f"LED controller at {self.url} speaks another protocol version")
                    self.stats.naks += 1
                    return "nak"
                if self._audit:
                    self.stats.accepted_crcs.append(item.crc)
                return item
            left = deadline - time.monotonic()
            if left <= 0:
                self.stats.timeouts += 1
                return "timeout"
            data = self._port.read(max(1, self._port.in_waiting))
            if data:
                if self._head is not None:
                    self._spot_handshake(data)
                self.stats.bytes_received += len(data)
                self._pending.extend(self._reader.feed(data))

    def _exchange(self, cmd: int, payload: bytes = b"", reply_max: int = REPLY_MAX) -> Frame:
        self.stats.commands += 1
        self._seq = (self._seq + 1) & 0xFFFF
        wire = encode_frame(cmd, self._seq, payload)
        wait = self.timeout_s + (len(wire) + reply_max) / self._rate()
        failures: dict[str, int] = {}
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats.retransmissions += 1
                time.sleep(min(self.backoff_s * 2 ** (attempt - 1), 1.0))
            try:
                self._send(wire)
                outcome = self._await(self._seq, cmd, time.monotonic() + wait)
            except (serial.SerialException, OSError) as e:  # unplugged, or the emulator restarted
                outcome = f"link error ({e})"
                try:
                    self._reopen()
                except DeviceError:
                    pass
            if isinstance(outcome, Frame):
                return outcome
            failures[outcome] = failures.get(outcome, 0) + 1
        summary = ", ".join(f"{n} {why}" for why, n in failures.items())
        raise DeviceError(f"LED controller at {self.url}: no valid reply to {Cmd(cmd).name} after "
                          f"{self.retries + 1} attempts ({summary})")

    def _command(self, cmd: int, payload: bytes = b"", reply_max: int = REPLY_MAX) -> tuple[State, bytes]:
        frame = self._exchange(cmd, payload, reply_max)
        state = State.unpack(frame.payload)
        if state.boot_id != self.boot_id:
            first = self.boot_id is None
            self.boot_id = state.boot_id
            if not first:
                self.stats.reboots += 1
                if cmd not in (Cmd.HELLO, Cmd.LIST, Cmd.RESET):
                    self._sync()
                    raise _Rebooted
        return state, frame.payload[STATE.size:]

    # --- slots ----------------------------------------------------------------------------------------
    def _sync(self) -> None:
        """Rebuild the slot table from the controller's (LIST): after connecting and after a reset."""
        state, data = self._command(Cmd.LIST, reply_max=2 * MAX_PAYLOAD)
        self._slot_of: dict[int, int] = {}     # crc -> slot holding it
        self._content: dict[int, bytes | None] = {}  # slot -> its bytes, when known (None: unknown)
        self._lru: OrderedDict[int, None] = OrderedDict()
        for slot in range(self.info.slots):
            flag, crc = LIST_ENTRY.unpack_from(data, slot * LIST_ENTRY.size)
            if flag == SlotFlag.EMPTY:
                self._content[slot] = bytes(self.size)
            elif flag == SlotFlag.VALID:
                self._slot_of.setdefault(crc, slot)
                self._content[slot] = self._patterns.get(crc)
                self._lru[slot] = None
            else:
                self._content[slot] = None
        self._displayed_slot = state.displayed_slot

    def _free_slot(self) -> int:
        """An empty slot, else one holding unknown bytes, else the least recently used pattern not lit."""
        used = set(self._slot_of.values())
        free = [s for s in range(self.info.slots) if s not in used]
        empty = [s for s in free if self._content.get(s) is not None]
        if empty or free:
            return (empty or free)[0]
        for slot in self._lru:
            if slot != self._displayed_slot:
                return slot
        raise DeviceError(f"LED controller at {self.url} has a single slot, which is lit")

    def _upload(self, data: bytes, crc: int) -> int:
        slot = self._free_slot()
        for c in [c for c, s in self._slot_of.items() if s == slot]:
            del self._slot_of[c]
        self._lru.pop(slot, None)
        runs = changed_runs(self._content.get(slot), data)
        self._content[slot] = None  # unknown until committed
        for payload in write_chunks(slot, data, runs):
            self._expect_ok(Cmd.WRITE, payload)
            self.stats.pattern_bytes_written += len(payload) - 6
        state, _ = self._command(Cmd.COMMIT, SLOT_CRC.pack(slot, crc))
        if state.status != Status.OK:
            return -1  # the slot did not hold what we thought (MISMATCH): its content stays unknown
        self.stats.uploads += 1
        self._slot_of[crc], self._content[slot] = slot, data
        self._lru[slot] = None
        return slot

    def _expect_ok(self, cmd: int, payload: bytes) -> State:
        state, _ = self._command(cmd, payload)
        if state.status != Status.OK:
            raise DeviceError(f"LED controller at {self.url} refused {Cmd(cmd).name}: {Status(state.status).name}")
        return state

    # --- the API --------------------------------------------------------------------------------------
    def _as_bytes(self, levels) -> bytes:
        """A pattern as the controller stores it: LED i's R, G, B at bytes 3i..3i+2 (uint8 (L, 3) or bytes)."""
        if isinstance(levels, (bytes, bytearray)):
            data = bytes(levels)
        elif np.asarray(levels).dtype == np.uint8:
            data = np.ascontiguousarray(levels).tobytes()
        else:
            raise DeviceError(f"LED levels must be uint8, got {np.asarray(levels).dtype}")
        if len(data) != self.size:
            raise DeviceError(f"a pattern for this controller is {self.size} bytes, got {len(data)}")
        return data

    def load(self, levels) -> int:
        """Make sure the pattern is stored in a slot (uploading what is needed); returns its CRC."""
        data = self._as_bytes(levels)
        crc = crc32(data)
        self._patterns[crc] = data
        for _ in range(self.retries + 1):
            try:
                if crc in self._slot_of:
                    return crc
                if self._upload(data, crc) >= 0:
                    return crc
            except _Rebooted:
                continue
        raise DeviceError(f"LED controller at {self.url}: could not store a pattern after {self.retries + 1} tries")

    def show(self, levels) -> State:
        """Latch the pattern onto the LEDs; returns the acknowledged state (displayed_crc == the pattern's)."""
        data = self._as_bytes(levels)
        crc = crc32(data)
        for _ in range(self.retries + 1):
            self.load(data)
            slot = self._slot_of[crc]
            try:
                state, _ = self._command(Cmd.SHOW, SLOT_CRC.pack(slot, crc))
            except _Rebooted:
                continue
            if state.status == Status.OK and state.displayed_crc == crc:
                self._displayed_slot = slot
                self._lru.move_to_end(slot)
                return state
            # the slot lost its pattern (SLOT/MISMATCH): forget it, store it again
            del self._slot_of[crc]
            self._content[slot] = None
        raise DeviceError(f"LED controller at {self.url}: could not display a pattern after {self.retries + 1} tries")

    def stored(self) -> dict[int, int]:
        """CRC -> slot of every pattern the controller holds committed."""
        return dict(self._slot_of)

    def query(self) -> State:
        return self._command_any(Cmd.STATE)[0]

    def reset(self) -> State:
        state = self._command_any(Cmd.RESET)[0]
        self._sync()
        return state

    def read(self, slot: int, offset: int = 0, length: int | None = None) -> bytes:
        """Bytes of a slot (NO_SLOT: the display buffer), READ by READ in MAX_CHUNK pieces."""
        length = self.size - offset if length is None else length
        out = bytearray()
        while len(out) < length:
            n = min(MAX_CHUNK, length - len(out))
            state, data = self._command_any(Cmd.READ, READ_ARGS.pack(slot, offset + len(out), n), 2 * MAX_PAYLOAD)
            if state.status != Status.OK:
                raise DeviceError(f"LED controller at {self.url} refused READ: {Status(state.status).name}")
            out += data
        return bytes(out)

    def _command_any(self, cmd: int, payload: bytes = b"", reply_max: int = REPLY_MAX):
        """A command whose result stands whether or not the controller reset just before it."""
        for _ in range(2):
            try:
                return self._command(cmd, payload, reply_max)
            except _Rebooted:
                continue
        return self._command(cmd, payload, reply_max)

