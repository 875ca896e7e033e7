"""What a capture design costs the device (docs/designer.md): pattern upload, acquisition time, LED duty.

Upload (`upload_cost`): each frame as the host sends it (twin.capture.backends.led_host): the WRITE chunks of the
bytes that differ from an empty (zeroed) slot, a COMMIT and, per photo, a SHOW, each led by the host's
resynchronising delimiter; every command is answered by a STATE reply. The bytes are the protocol's own
encoding (`encode_frame`: COBS, header, CRC32; checked against the emulator's link counters in the tests); the time is bytes / (baud / 10) (8N1: 10 bits a byte) plus one turnaround latency per command
(docs/led-protocol.md section 7 derives the same for a whole 49,152-byte pattern).

Acquisition (`acquisition_time`): per photo, the sum of its bracket's exposures plus a fixed overhead per raw
frame (readout, trigger); the cameras of a view are triggered together, so a photo taken by both cameras costs
its longer bracket once; a frame with no LED lit is not photographed (its value is 0).

Duty (`led_duty`): per LED, the peak drive (level / 255) over the frames and the exposure-weighted mean drive
over the capture (the fraction of the time the LED spends at full drive, its thermal load).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.capture.backends.led_protocol import (REPLY, SLOT_CRC, STATE, Cmd, changed_runs, crc32, encode_frame,
                                                write_chunks)


@dataclass(frozen=True)
class UploadCost:
    commands: int
    bytes_out: int
    bytes_back: int
    seconds: float


def _reply_bytes(cmd: int, extra: int = 0) -> int:
    """A reply: the controller's STATE, then `extra` bytes (COMMIT answers with the slot's CRC32)."""
    return len(encode_frame(cmd | REPLY, 0, bytes(STATE.size + extra)))


def upload_cost(levels: np.ndarray, baud: int, latency_s: float, shows: int | None = None) -> UploadCost:
    """Storing the frames `levels` (F, L, 3) uint8 in empty slots and showing each once (or `shows` times in
    all): the commands, the bytes each way and the time at `baud` with `latency_s` per command."""
    lv = np.asarray(levels)
    if lv.ndim != 3 or lv.shape[2] != 3 or lv.dtype != np.uint8:
        raise ValueError(f"levels must be (F, L, 3) uint8, got {lv.shape} {lv.dtype}")
    if not (isinstance(baud, (int, np.integer)) and baud > 0) or not (np.isfinite(latency_s) and latency_s >= 0):
        raise ValueError(f"baud must be a positive integer and latency_s >= 0, got {baud!r}, {latency_s!r}")
    empty = bytes(lv.shape[1] * 3)
    commands = out = back = 0
    for slot, frame in enumerate(lv):
        data = np.ascontiguousarray(frame).tobytes()
        for payload in write_chunks(slot % 65536, data, changed_runs(empty, data)):
            out += len(encode_frame(Cmd.WRITE, commands, payload)) + 1
            back += _reply_bytes(Cmd.WRITE)
            commands += 1
        out += len(encode_frame(Cmd.COMMIT, commands, SLOT_CRC.pack(slot % 65536, crc32(data)))) + 1
        back += _reply_bytes(Cmd.COMMIT, 4)
        commands += 1
    for _ in range(len(lv) if shows is None else int(shows)):
        out += len(encode_frame(Cmd.SHOW, commands, SLOT_CRC.pack(0, 0))) + 1
        back += _reply_bytes(Cmd.SHOW)
        commands += 1
    return UploadCost(commands, out, back, (out + back) / (baud / 10.0) + commands * latency_s)


def acquisition_time(exposures_s: np.ndarray, frame_overhead_s: float) -> float:
    """Seconds to take photos whose brackets are `exposures_s` (P, cameras, bracket): per photo the longest
    camera's bracket (the cameras are triggered together), each raw frame plus `frame_overhead_s`. A photo
    whose exposures are all 0 (a frame with no LED lit: its value is known to be 0) is not taken."""
    return float(photo_seconds(exposures_s, frame_overhead_s).sum())


def photo_seconds(exposures_s: np.ndarray, frame_overhead_s: float) -> np.ndarray:
    """(P,) the time each photo of `acquisition_time` takes."""
    e = np.asarray(exposures_s, dtype=np.float64)
    if e.ndim != 3 or not np.isfinite(e).all() or (e < 0).any():
        raise ValueError(f"exposures_s must be (photos, cameras, bracket) finite and >= 0, got shape {e.shape}")
    taken = (e > 0).any(axis=(1, 2))
    return np.where(taken, (e.sum(axis=2) + e.shape[2] * frame_overhead_s).max(axis=1), 0.0)


def led_duty(levels: np.ndarray, photo_seconds: np.ndarray) -> dict:
    """Per LED (L,): `peak` drive (level / 255, max over frames) and `mean` drive weighted by each frame's time
    on (`photo_seconds` (F,)) over the whole time; LEDs never driven have 0."""
    lv = np.asarray(levels)
    t = np.asarray(photo_seconds, dtype=np.float64)
    if lv.ndim != 3 or t.shape != (lv.shape[0],) or not np.isfinite(t).all() or (t < 0).any():
        raise ValueError(f"levels (F, L, 3) and photo_seconds (F,) >= 0 must match, got {lv.shape} and {t.shape}")
    drive = lv.astype(np.float64).max(axis=2) / 255.0  # an LED's hottest channel
    total = t.sum()
    return {"peak": drive.max(axis=0, initial=0.0),
            "mean": (t @ drive) / total if total > 0 else np.zeros(lv.shape[1])}
