"""The emulator's end of its link (`hemicube controller serve`, docs/led-protocol.md section 1.1): where it listens
(loopback, unless another address is explicitly allowed, and then only with a token), whom it admits (the token
handshake of led_auth), and how long a host may hold it without a word (the idle timeout), so that one host,
careless or hostile, cannot keep the others out."""
from __future__ import annotations

import errno
import ipaddress
import os
import select
import socket
import time

from twin.capture.backends import led_auth
from twin.capture.plan import CaptureError


def listen_address(link: str, allow_remote: bool, token: bytes | None) -> tuple[int, tuple]:
    """socket://HOST:PORT -> (address family, address to bind). Loopback unless `allow_remote`, which needs a
    token: any host that reaches the port could otherwise light the LEDs and read what the controller holds."""
    host, _, port = link[len("socket://"):].rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host  # [::1]: an IPv6 address
    if not port.isdigit() or int(port) > 0xFFFF:
        raise CaptureError(f"--link {link}: the port must be 0..65535 (0: any free port)")
    try:
        family, _, _, _, address = socket.getaddrinfo(host or "127.0.0.1", int(port), type=socket.SOCK_STREAM,
                                                      flags=socket.AI_PASSIVE)[0]
    except socket.gaierror as e:
        raise CaptureError(f"--link {link}: cannot resolve {host!r} ({e.strerror})") from None
    ip = ipaddress.ip_address(address[0].partition("%")[0])
    if not ip.is_loopback:
        where = "every interface" if ip.is_unspecified else f"{ip}, not a loopback address"
        if not allow_remote:
            raise CaptureError(f"--link {link} listens on {where}, where other hosts could drive the LEDs: "
                               "listen on 127.0.0.1, or add --allow-remote (with a token) to mean it")
        if token is None:
            raise CaptureError(f"--allow-remote needs a token: --token-file FILE or {led_auth.TOKEN_ENV}")
    return family, address


def open_link(link: str, allow_remote: bool, token: bytes | None):
    """-> (url to print, listening socket or None, pty master fd or None, slave fd or None)."""
    if link == "pty":
        import tty

        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)  # kept open so that the pty survives the host closing it between connections
        return os.ttyname(slave), None, master, slave
    if not link.startswith("socket://"):
        raise CaptureError(f"--link must be socket://HOST:PORT or pty, got {link!r}")
    family, address = listen_address(link, allow_remote, token)
    try:
        srv = socket.create_server(address, family=family)
    except OSError as e:
        why = {errno.EADDRINUSE: f"port {address[1]} is in use",
               errno.EADDRNOTAVAIL: f"{address[0]} is not an address of this machine"}.get(e.errno, e.strerror)
        raise CaptureError(f"--link {link}: cannot listen: {why}") from None
    h, p = srv.getsockname()[:2]
    return f"socket://{f'[{h}]' if family == socket.AF_INET6 else h}:{p}", srv, None, None


def admitted(conn, token: bytes, timeout_s: float) -> bool:
    """The token handshake with a host that just connected: whether it proved it holds the token."""
    def read_some(left: float) -> bytes:
        if not select.select([conn], [], [], left)[0]:
            return b""
        data = conn.recv(led_auth.LINE_MAX)
        if not data:
            raise led_auth.HandshakeError("the host closed the link")
        return data

    deadline = time.monotonic() + timeout_s
    try:
        return led_auth.controller(token, conn.sendall, lambda: led_auth.read_line(read_some, deadline))
    except OSError:
        return False


def pump(fileobj, receive, send, recv, idle_s: float | None = None) -> str:
    """Feed `receive(data, send)` from one link until the host goes away (a socket's EOF; a pty never ends) or
    sends nothing for `idle_s` seconds; returns which: 'closed' or 'idle'."""
    while True:
        if not select.select([fileobj], [], [], idle_s)[0]:
            return "idle"
        try:
            data = recv()
        except OSError:
            return "closed"
        if not data:
            return "closed"
        try:
            receive(data, send)
        except (BrokenPipeError, ConnectionResetError):
            return "closed"
