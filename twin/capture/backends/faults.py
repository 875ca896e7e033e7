"""Faults injected into the emulated devices, from a spec such as `corrupt=0.01,flip=1e-5,seed=3`, and their
seeded decisions: the LED controller's link (`Faults`, used by the firmware emulator) and the emulated
cameras (`CameraFaults`, used by the pylon backend). docs/led-protocol.md and docs/reliability.md define the
kinds."""
from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

from twin.capture.plan import CaptureError

FAULT_KINDS = {  # LED link: kind -> the directions it applies to ("in": host to device, "out": device to host)
    "drop": ("in", "out"),      # one byte of the frame removed
    "corrupt": ("in", "out"),   # one byte of the frame XORed with a random non-zero value
    "dup": ("in", "out"),       # the frame twice in a row
    "delay": ("in", "out"),     # the frame held back for delay_s
    "reset": ("in",),           # the device resets part-way through receiving the frame
    "stuck": ("out",),          # the device repeats its previous reply instead of this one
}
CAMERA_FAULT_KINDS = {  # emulated cameras: kind -> what happens before a trigger
    "failed": "the next frame arrives as a failed (incomplete) buffer (pylon's ForceFailedBuffer)",
    "disconnect": "the camera is unplugged (pylon's FirePnPCallback): reopen, reconfigure, retake",
    "stray": "a trigger that is not ours exposes an extra frame",
}


def parse_spec(text: str | None, option: str, kinds, numbers: dict[str, bool]) -> tuple[dict, dict, int]:
    """'KIND=P,...,NAME=X,...,seed=N' -> (probability by kind, value by number name, seed). `numbers` maps
    each extra name to whether it is a probability (else any non-negative number)."""
    grammar = (f"comma-separated KIND=P (KIND: {', '.join(kinds)}; P a probability)"
               + "".join(f", {n}=X" for n in numbers) + ", seed=N")
    rates, values, seed = {}, {}, 0
    for item in filter(None, (s.strip() for s in (text or "").split(","))):
        key, eq, value = item.partition("=")
        try:
            if not eq:
                raise ValueError
            if key == "seed":
                seed = int(value)
                continue
            v = float(value)
        except ValueError:
            raise CaptureError(f"{option}: {item!r} is not KEY=NUMBER; expected {grammar}") from None
        probability = key in kinds or numbers.get(key, False)
        if key not in kinds and key not in numbers:
            raise CaptureError(f"{option}: unknown {key!r}; expected {grammar}")
        if not (0.0 <= v <= 1.0 if probability else 0.0 <= v < math.inf):
            raise CaptureError(f"{option}: {key} must be {'a probability in [0, 1]' if probability else '>= 0'}, "
                               f"got {value}")
        (rates if key in kinds else values)[key] = v
    return rates, values, seed


@dataclass
class FaultSpec:
    """The LED link's faults: per-frame probabilities by kind, bit errors per byte, the delay, the seed; and
    `brownout`, the probability that latching a pattern browns the controller out: it acknowledges the SHOW,
    then restarts (LEDs off, slots empty, a new boot id) before the host's next command, as a supply too weak
    for the LEDs' switch-on current would. The capture's next command after a SHOW is its metering's."""
    rates: dict = field(default_factory=dict)
    flip: float = 0.0
    delay_s: float = 0.5
    seed: int = 0
    brownout: float = 0.0

    @classmethod
    def parse(cls, text: str | None) -> "FaultSpec":
        rates, values, seed = parse_spec(text, "--faults", FAULT_KINDS,
                                         {"flip": True, "delay_s": False, "brownout": True})
        for d in ("in", "out"):
            total = sum(p for k, p in rates.items() if d in FAULT_KINDS[k])
            if total > 1.0:
                raise CaptureError(f"--faults: the per-frame probabilities of one direction sum to {total:g} > 1")
        return cls(rates, values.get("flip", 0.0), values.get("delay_s", 0.5), seed, values.get("brownout", 0.0))

    def __str__(self):
        parts = ([f"{k}={v:g}" for k, v in self.rates.items()] + ([f"flip={self.flip:g}"] if self.flip else [])
                 + ([f"brownout={self.brownout:g}"] if self.brownout else []))
        return ",".join(parts + [f"delay_s={self.delay_s:g}", f"seed={self.seed}"]) if parts else "none"


class _Picker:
    """At most one of the kinds per event, each with its probability, from one seeded stream."""

    def __init__(self, rates: dict, seed: int):
        self.rates = rates
        self._rng = random.Random(seed)
        self.counts: dict[str, int] = {}

    def _pick(self, kinds, tag: str = "") -> str | None:
        u = self._rng.random()
        for kind in kinds:
            p = self.rates[kind]
            if u < p:
                key = f"{kind}_{tag}" if tag else kind
                self.counts[key] = self.counts.get(key, 0) + 1
                return kind
            u -= p
        return None


class Faults(_Picker):
    """The LED link's fault decisions: at most one frame fault per frame, then independent bit errors."""

    def __init__(self, spec: FaultSpec):
        super().__init__(spec.rates, spec.seed)
        self.spec = spec
        self._until_flip = {"in": self._gap(), "out": self._gap()}

    def _gap(self) -> float:
        """Bytes before the next bit error (geometric), so that clean bytes cost nothing to decide."""
        q = self.spec.flip
        if q <= 0:
            return math.inf
        if q >= 1:
            return 0
        return int(math.log(1.0 - self._rng.random()) / math.log1p(-q))

    def pick(self, direction: str) -> str | None:
        return self._pick([k for k in self.rates if direction in FAULT_KINDS[k]], direction)

    def brownout(self) -> bool:
        """Whether the pattern just latched browns the controller out (drawn only when the spec has brownouts,
        so that every other spec keeps its sequence of decisions)."""
        if self.spec.brownout <= 0 or self._rng.random() >= self.spec.brownout:
            return False
        self.counts["brownout"] = self.counts.get("brownout", 0) + 1
        return True

    def damage(self, wire: bytes, kind: str) -> bytes:
        """drop/corrupt one byte of a frame's encoded bytes (never its delimiter: bit errors cover that)."""
        i = self._rng.randrange(len(wire) - 1)
        if kind == "drop":
            return wire[:i] + wire[i + 1:]
        return wire[:i] + bytes([wire[i] ^ self._rng.randrange(1, 256)]) + wire[i + 1:]

    def flips(self, data: bytes, direction: str) -> tuple[bytes, int]:
        """`data` with this direction's bit errors applied, and how many."""
        n = 0
        buf = None
        pos = self._until_flip[direction]
        while pos < len(data):
            buf = buf or bytearray(data)
            buf[int(pos)] ^= 1 << self._rng.randrange(8)
            n += 1
            pos += 1 + self._gap()
        self._until_flip[direction] = pos - len(data)
        if n:
            self.counts[f"flip_{direction}"] = self.counts.get(f"flip_{direction}", 0) + n
        return (bytes(buf) if buf is not None else data), n


class CameraFaults(_Picker):
    """The emulated cameras' fault decisions, one per trigger."""

    def __init__(self, text: str | None):
        rates, _, seed = parse_spec(text, "--camera-faults", CAMERA_FAULT_KINDS, {})
        if sum(rates.values()) > 1.0:
            raise CaptureError(f"--camera-faults: the probabilities sum to {sum(rates.values()):g} > 1")
        super().__init__(rates, seed)

    def pick(self) -> str | None:
        return self._pick(list(self.rates))
