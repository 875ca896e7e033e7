"""The LED controller's wire protocol, shared by the host (`led_host`) and the firmware emulator
(`led_emulator`); `docs/led-protocol.md` is its specification. Pure Python and no I/O, so the framing can
be tested byte by byte.

A frame on the wire is COBS(body) followed by one 0x00 delimiter, where

    body = type u8 | version u8 | seq u16 | length u16 | payload (length bytes) | crc32 u32

little-endian, and crc32 is CRC-32/IEEE 802.3 (zlib's) over everything before it. COBS removes every 0x00
from the body, so 0x00 only ever ends a frame: a receiver that lost track resynchronises at the next one.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from enum import IntEnum

VERSION = 1
HEADER = struct.Struct("<BBHH")  # type, version, seq, payload length
CRC = struct.Struct("<I")
MAX_CHUNK = 4096  # pattern bytes per WRITE or READ: a 49,152-byte pattern is 12 frames
WRITE_HEAD = struct.Struct("<HI")  # slot, byte offset
STATE = struct.Struct("<BIHII")  # status, boot_id, displayed_slot, displayed_crc, rejected frames
MAX_PAYLOAD = STATE.size + MAX_CHUNK  # 4,111 (a READ reply): the largest payload of any frame, either way
MAX_BODY = HEADER.size + MAX_PAYLOAD + CRC.size
DELIMITER = 0


def cobs_size(n: int) -> int:
    """The largest COBS encoding of n bytes (one code byte per 254-byte run, plus the first)."""
    return n + 1 + n // 254


MAX_WIRE = cobs_size(MAX_BODY) + 1  # with its delimiter: longer runs without a 0x00 are garbage


class Cmd(IntEnum):
    HELLO = 0x01   # -> state + device description
    STATE = 0x02   # -> state
    WRITE = 0x03   # slot u16, offset u32, data -> state
    COMMIT = 0x04  # slot u16, crc u32 -> state (slot valid when the CRC of its bytes matches)
    SHOW = 0x05    # slot u16, crc u32 -> state (the slot latched onto the LEDs)
    LIST = 0x06    # -> state + per slot: flag u8, crc u32
    READ = 0x07    # slot u16 (0xFFFF: the display), offset u32, length u16 -> state + bytes
    RESET = 0x08   # -> state after the reset


REPLY = 0x80  # a reply's type is its command's type | REPLY
NAK = 0xFF    # the reply to a frame that failed its checks (its seq is only as good as the damaged header)


class Status(IntEnum):
    OK = 0
    FRAME = 1      # COBS, length or CRC check failed: the frame was dropped
    VERSION = 2    # the frame's protocol version is not the device's
    UNKNOWN = 3    # unknown command type
    LENGTH = 4     # payload length wrong for the command
    SLOT = 5       # no such slot, or (SHOW) the slot holds no committed pattern
    RANGE = 6      # WRITE/READ beyond the pattern
    MISMATCH = 7   # COMMIT/SHOW: the slot's CRC is not the one given


class SlotFlag(IntEnum):
    EMPTY = 0  # all zeros since boot
    DIRTY = 1  # written since its last commit
    VALID = 2  # committed: its CRC is known


NO_SLOT = 0xFFFF  # displayed_slot at boot (all LEDs off), and READ's "the display buffer"
HELLO_INFO = struct.Struct("<HBHHH")  # protocol version, bytes per LED, LEDs, slots, max payload
SLOT_CRC = struct.Struct("<HI")
READ_ARGS = struct.Struct("<HIH")
LIST_ENTRY = struct.Struct("<BI")


def crc32(data) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


def cobs_encode(data: bytes) -> bytes:
    out = bytearray()
    for block in bytes(data).split(b"\x00"):  # each 0x00 ends a block; a code byte < 0xFF implies it
        while len(block) >= 254:
            out.append(0xFF)  # 254 bytes and no implied zero
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(enc: bytes) -> bytes:
    out = bytearray()
    i, n = 0, len(enc)
    while i < n:
        code = enc[i]
        end = i + code
        if code == 0 or end > n:
            raise ValueError("bad COBS code")
        out += enc[i + 1:end]
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


@dataclass(frozen=True)
class Frame:
    type: int
    seq: int
    payload: bytes
    crc: int  # the frame's own CRC field (with seq, what a retransmission repeats exactly)


class FrameError(ValueError):
    """A frame that failed COBS, length or CRC checks; `seq` is the damaged header's, if it had one."""

    def __init__(self, reason: str, seq: int | None = None, version_ok: bool = True):
        super().__init__(reason)
        self.seq = seq
        self.version_ok = version_ok


def encode_frame(type_: int, seq: int, payload: bytes = b"") -> bytes:
    """The wire bytes of one frame, delimiter included."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds the protocol's {MAX_PAYLOAD}")
    head = HEADER.pack(type_, VERSION, seq & 0xFFFF, len(payload)) + payload
    return cobs_encode(head + CRC.pack(crc32(head))) + b"\x00"


def decode_frame(enc: bytes) -> Frame:
    """One frame's COBS bytes (without the delimiter) -> Frame, else FrameError."""
    try:
        body = cobs_decode(enc)
    except ValueError:
        raise FrameError("COBS") from None
    if len(body) < HEADER.size + CRC.size:
        raise FrameError("short")
    type_, version, seq, length = HEADER.unpack_from(body)
    if length > MAX_PAYLOAD or len(body) != HEADER.size + length + CRC.size:
        raise FrameError("length", seq)
    (crc,) = CRC.unpack_from(body, len(body) - CRC.size)
    if crc32(memoryview(body)[:-CRC.size]) != crc:
        raise FrameError("CRC", seq)
    if version != VERSION:
        raise FrameError("version", seq, version_ok=False)
    return Frame(type_, seq, body[HEADER.size:-CRC.size], crc)


class FrameReader:
    """Splits a byte stream into frames at 0x00 delimiters. `feed` returns, in order, a Frame or a
    FrameError for each complete frame; empty frames (back-to-back delimiters) are skipped, and a run longer
    than MAX_WIRE without a delimiter is dropped as one error (resynchronising at the next delimiter)."""

    def __init__(self):
        self._buf = bytearray()
        self._overrun = False

    @property
    def dropping(self) -> bool:
        """Whether the bytes up to the next delimiter are the rest of an over-long run, already reported."""
        return self._overrun

    def feed(self, data: bytes) -> list:
        out = []
        self._buf += data
        while True:
            end = self._buf.find(0)
            if end < 0:
                if len(self._buf) > MAX_WIRE:
                    self._buf.clear()
                    if not self._overrun:
                        out.append(FrameError("overrun"))
                    self._overrun = True
                return out
            piece = bytes(self._buf[:end])
            del self._buf[:end + 1]
            if self._overrun:  # the tail of a run already reported
                self._overrun = False
                continue
            if piece:
                try:
                    out.append(decode_frame(piece))
                except FrameError as e:
                    out.append(e)


@dataclass(frozen=True)
class State:
    """The state block every reply starts with: what the device displays now."""
    status: int
    boot_id: int
    displayed_slot: int
    displayed_crc: int
    rejected: int

    def pack(self) -> bytes:
        return STATE.pack(self.status, self.boot_id, self.displayed_slot, self.displayed_crc, self.rejected)

    @classmethod
    def unpack(cls, payload: bytes) -> "State":
        if len(payload) < STATE.size:
            raise FrameError("reply shorter than its state block")
        return cls(*STATE.unpack_from(payload))


@dataclass(frozen=True)
class DeviceInfo:
    version: int
    bytes_per_led: int
    num_leds: int
    slots: int
    max_payload: int
    firmware: str

    def pack(self) -> bytes:
        return HELLO_INFO.pack(self.version, self.bytes_per_led, self.num_leds, self.slots,
                               self.max_payload) + self.firmware.encode()

    @classmethod
    def unpack(cls, data: bytes) -> "DeviceInfo":
        return cls(*HELLO_INFO.unpack_from(data), data[HELLO_INFO.size:].decode(errors="replace"))


def write_chunks(slot: int, data: bytes, runs) -> list[bytes]:
    """WRITE payloads carrying data[a:b] for each (a, b) of `runs`, split at MAX_CHUNK."""
    out = []
    for a, b in runs:
        for off in range(a, b, MAX_CHUNK):
            out.append(WRITE_HEAD.pack(slot, off) + data[off:min(b, off + MAX_CHUNK)])
    return out


def changed_runs(old: bytes | None, new: bytes, gap: int = 16) -> list[tuple[int, int]]:
    """Byte ranges [a, b) where `new` differs from `old` (all of it when `old` is unknown or most of it
    changed), merging runs less than `gap` bytes apart: a new WRITE costs about 20 bytes of framing, so short
    gaps are cheaper sent than skipped."""
    import numpy as np

    changed = None if old is None else np.frombuffer(old, np.uint8) != np.frombuffer(new, np.uint8)
    if changed is None or 2 * np.count_nonzero(changed) > len(new):
        return [(0, len(new))] if new else []
    diff = np.flatnonzero(changed)
    if diff.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(diff) > gap)
    starts = np.r_[diff[0], diff[breaks + 1]]
    ends = np.r_[diff[breaks], diff[-1]] + 1
    return list(zip(starts.tolist(), ends.tolist()))
