"""The token handshake that opens a TCP link to the LED controller when a token is set (docs/led-protocol.md,
section 1.1), for both ends: the host (`led_host`) and the emulator (`led_emulator`).

It comes before the first frame, in lines of ASCII, so the frame protocol stays version 1. Neither end sends the
token: each sends an HMAC-SHA256, under the token, of both ends' fresh nonces, so that a proof overheard on the
network opens no later link, and the host learns that it talks to a controller that holds the token as well:

    host -> controller   HCLED-AUTH1 <host nonce>
    controller -> host   HCLED-AUTH1 <controller nonce> <HMAC(token, "controller <host nonce> <controller nonce>")>
    host -> controller   HCLED-AUTH1 <HMAC(token, "host <host nonce> <controller nonce>")>
    controller -> host   HCLED-AUTH1 ok           (or `refused`, and the controller closes the link)

Nonces are 32 lowercase hex digits (128 random bits), proofs 64; every line ends with one \\n.
"""
from __future__ import annotations

import hashlib
import hmac
import os
import re
import secrets
import time
from pathlib import Path

from twin.capture.plan import CaptureError

TOKEN_ENV = "HEMICUBE_LED_TOKEN"
MIN_TOKEN = 16  # characters: a token short enough to guess is no token
MAGIC = b"HCLED-AUTH1 "
LINE_MAX = 128  # the longest line is the controller's, 110 bytes
TIMEOUT_S = 5.0  # for a whole handshake, at either end
_HEX = re.compile(rb"[0-9a-f]+")


class HandshakeError(Exception):
    """The other end did not complete the handshake; the message says how."""


def load_token(path=None) -> bytes | None:
    """The shared token: the first line of the file `path` when given, else $HEMICUBE_LED_TOKEN, else None. The
    token itself is never part of a message."""
    if path is not None:
        where = f"--token-file {path}"
        try:
            lines = Path(path).read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise CaptureError(f"{where}: {getattr(e, 'strerror', None) or 'not a text file'}") from None
        text = lines[0].strip() if lines else ""
    else:
        where, text = TOKEN_ENV, os.environ.get(TOKEN_ENV)
        if text is None:
            return None
        text = text.strip()
    if len(text) < MIN_TOKEN:
        raise CaptureError(f"{where}: a token has at least {MIN_TOKEN} characters, e.g. "
                           "`python -c 'import secrets; print(secrets.token_hex(16))'`")
    return text.encode()


def _proof(token: bytes, role: str, host_nonce: str, controller_nonce: str) -> str:
    return hmac.new(token, f"{role} {host_nonce} {controller_nonce}".encode(), hashlib.sha256).hexdigest()


def _line(*fields: str) -> bytes:
    return MAGIC + " ".join(fields).encode() + b"\n"


def _fields(line: bytes, *digits: int) -> list[str]:
    """A line's hex fields, of `digits` hex digits each; HandshakeError if it is not that line."""
    fields = line[len(MAGIC):-1].split(b" ")
    if len(fields) != len(digits) or any(len(f) != n or not _HEX.fullmatch(f) for f, n in zip(fields, digits)):
        raise HandshakeError("an unexpected handshake line")
    return [f.decode() for f in fields]


def read_line(read_some, deadline: float) -> bytes:
    """One handshake line, read with `read_some(seconds left)` (bytes; b'' when none came in time) by the
    monotonic `deadline`. Bytes that cannot begin a handshake line (a frame, from a host that has no token) fail
    at once rather than at the deadline."""
    buf = b""
    while b"\n" not in buf:
        if not MAGIC.startswith(buf[:len(MAGIC)]) or len(buf) > LINE_MAX:
            raise HandshakeError("bytes that are no handshake line")
        left = deadline - time.monotonic()
        if left <= 0:
            raise HandshakeError("no handshake line in time")
        buf += read_some(left)
    if not buf.endswith(b"\n"):  # each end waits for the other's line before it sends the next
        raise HandshakeError("bytes after a handshake line")
    return buf


def host(token: bytes, send, read) -> None:
    """The host's end: `send(bytes)`, `read()` -> one line (read_line). Returns once the link carries frames;
    HandshakeError if the controller does not prove it holds the token, or refuses ours."""
    host_nonce = secrets.token_hex(16)
    send(_line(host_nonce))
    controller_nonce, theirs = _fields(read(), 32, 64)
    if not hmac.compare_digest(theirs, _proof(token, "controller", host_nonce, controller_nonce)):
        raise HandshakeError("it holds another token")
    send(_line(_proof(token, "host", host_nonce, controller_nonce)))
    if read() != _line("ok"):
        raise HandshakeError("it refused this token")


def controller(token: bytes, send, read) -> bool:
    """The controller's end: True when the host proved it holds the token; otherwise it is told `refused` (the
    caller then closes the link)."""
    try:
        (host_nonce,) = _fields(read(), 32)
        controller_nonce = secrets.token_hex(16)
        send(_line(controller_nonce, _proof(token, "controller", host_nonce, controller_nonce)))
        (answer,) = _fields(read(), 64)
        ok = hmac.compare_digest(answer, _proof(token, "host", host_nonce, controller_nonce))
    except HandshakeError:
        ok = False
    send(_line("ok" if ok else "refused"))
    return ok
