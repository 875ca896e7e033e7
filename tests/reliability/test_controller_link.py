"""The LED controller emulator's link (`hemicube controller serve`, docs/led-protocol.md section 1.1): loopback
unless told otherwise, a token every TCP host must prove it holds when one is set, a receive buffer that stays
bounded whatever arrives, an idle host dropped so that the next can connect, and every error of `serve` on one
line. Each test starts the emulator as its own process and talks to it over its socket."""
from __future__ import annotations

import argparse
import json
import os
import select
import socket
import subprocess
import sys
import time
from urllib.parse import urlsplit

import numpy as np
import pytest

from twin.capture.backends.led_emulator import add_arguments, spawn
from twin.capture.backends.led_host import LedController
from twin.capture.backends.led_protocol import REPLY, Cmd, State, crc32, decode_frame, encode_frame
from twin.capture.plan import DeviceError
from twin.exitcodes import EXIT_IO, EXIT_USAGE

LEDS = 460
TOKEN_ENV = "HEMICUBE_LED_TOKEN"
TOKEN = "4f1c9a0e-a shared secret of the rig"
EMULATOR = [sys.executable, "-m", "twin.capture.backends.led_emulator", "--leds", str(LEDS)]


def _address(url: str) -> tuple[str, int]:
    parts = urlsplit(url)
    return parts.hostname, parts.port


def _stop(proc) -> str:
    """Stop a spawned emulator; what it printed after its first line, on both streams."""
    proc.terminate()
    out, err = proc.communicate(timeout=10)
    return out + err


def _receive(sock, until: bytes | None) -> bytes:
    """What the controller sends until `until` arrives (None: until it closes the link), or 5 s pass."""
    got, deadline = b"", time.monotonic() + 5
    while (until is None or until not in got) and time.monotonic() < deadline:
        if select.select([sock], [], [], deadline - time.monotonic())[0]:
            data = sock.recv(65536)
            if not data:
                break
            got += data
    return got


def _command(sock, cmd: int, seq: int) -> State:
    """One command sent as a host sends it (after a delimiter), and the state its reply carries."""
    sock.sendall(b"\x00" + encode_frame(cmd, seq))
    reply = decode_frame(_receive(sock, b"\x00").split(b"\x00")[0])
    assert (reply.type, reply.seq) == (cmd | REPLY, seq)
    return State.unpack(reply.payload)


def _serve_error(*argv, token: str | None = None, code: int = EXIT_USAGE) -> str:
    """Start `serve` expecting it to stop at once with exit code `code`; the one line it wrote to stderr."""
    env = {**os.environ, **({TOKEN_ENV: token} if token else {})}
    try:
        done = subprocess.run(EMULATOR + [str(a) for a in argv], capture_output=True, text=True, timeout=10, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail(f"serve {argv} kept serving instead of refusing")
    assert (done.returncode, done.stdout) == (code, ""), done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("led_emulator: error: "), done.stderr
    return lines[0]


def test_a_tcp_host_must_prove_it_holds_the_token(tmp_path, monkeypatch):
    log = tmp_path / "led.jsonl"
    proc, url = spawn(LEDS, token=TOKEN, log=log, idle_timeout_s=1.0)
    patterns = np.random.default_rng(0).integers(0, 256, (2, LEDS, 3), dtype=np.uint8)
    try:
        with socket.create_connection(_address(url), timeout=5) as raw:  # a host that skips the handshake
            raw.sendall(b"\x00" + encode_frame(Cmd.HELLO, 1))
            assert _receive(raw, None) == b"HCLED-AUTH1 refused\n"  # not one frame, and the link closed
        monkeypatch.delenv(TOKEN_ENV, raising=False)
        with pytest.raises(DeviceError, match=f"asks for a token: set {TOKEN_ENV}"):
            LedController(url, LEDS)
        monkeypatch.setenv(TOKEN_ENV, "another token, as long as the rig's")
        with pytest.raises(DeviceError, match="holds another token"):
            LedController(url, LEDS)
        monkeypatch.setenv(TOKEN_ENV, TOKEN)
        with LedController(url, LEDS) as ctl:
            assert ctl.show(patterns[0]).displayed_crc == crc32(patterns[0].tobytes())
            time.sleep(1.5)  # dropped as idle: the next command reconnects, through the handshake again
            assert ctl.show(patterns[1]).displayed_crc == crc32(patterns[1].tobytes())
            assert ctl.stats.reconnects >= 1
    finally:
        printed = _stop(proc)
    events = [json.loads(line) for line in log.read_text().splitlines()]
    assert [e["event"] for e in events if e["event"] in ("refused", "display")] == ["refused"] * 3 + ["display"] * 2
    assert TOKEN not in printed + log.read_text()  # never printed nor logged


def test_every_interface_only_when_asked_and_with_a_token(monkeypatch):
    message = _serve_error("--link", "socket://0.0.0.0:0")
    assert "listens on every interface" in message and "--allow-remote" in message
    assert "needs a token" in _serve_error("--link", "socket://0.0.0.0:0", "--allow-remote")
    proc, url = spawn(LEDS, link="socket://:0")
    _stop(proc)
    assert _address(url)[0] == "127.0.0.1"  # loopback by default
    proc, url = spawn(LEDS, link="socket://0.0.0.0:0", allow_remote=True, token=TOKEN)
    try:
        monkeypatch.setenv(TOKEN_ENV, TOKEN)
        with LedController(f"socket://127.0.0.1:{_address(url)[1]}", LEDS) as ctl:
            assert ctl.info.num_leds == LEDS
    finally:
        _stop(proc)


def test_an_over_long_frame_is_dropped_as_it_arrives():
    proc, url = spawn(LEDS)
    try:
        rss = int(open(f"/proc/{proc.pid}/status").read().split("VmRSS:")[1].split()[0])  # KiB
        with socket.create_connection(_address(url), timeout=10) as raw:
            t0 = time.monotonic()
            raw.sendall(b"\x01" * (32 << 20))  # 32 MiB without a delimiter: no frame is that long
            state = _command(raw, Cmd.STATE, 1)
            took = time.monotonic() - t0
        peak = int(open(f"/proc/{proc.pid}/status").read().split("VmHWM:")[1].split()[0])
    finally:
        _stop(proc)
    assert state.rejected == 1  # dropped as one bad frame, and the next frame is answered
    assert took < 3.0 and peak - rss < 16 * 1024, (took, peak - rss)


def test_an_idle_host_is_dropped_so_that_another_can_connect(tmp_path):
    log = tmp_path / "led.jsonl"
    proc, url = spawn(LEDS, idle_timeout_s=0.5, log=log)
    try:
        with socket.create_connection(_address(url), timeout=10) as idle:
            _command(idle, Cmd.STATE, 1)  # served, then silent
            t0 = time.monotonic()
            with LedController(url, LEDS) as ctl:  # waits in the backlog until the idle host is dropped
                waited = time.monotonic() - t0
                assert ctl.query().rejected == 0
            assert _receive(idle, None) == b""  # the idle host's link was closed
    finally:
        _stop(proc)
    assert waited < 3.0
    reasons = [e.get("reason") for e in map(json.loads, log.read_text().splitlines()) if e["event"] == "disconnect"]
    assert reasons[0] == "idle"
    options = argparse.ArgumentParser()
    add_arguments(options)
    assert options.parse_args(["--link", "pty"]).idle_timeout == 30  # the default


@pytest.fixture
def busy_port():
    with socket.create_server(("127.0.0.1", 0)) as s:
        yield s.getsockname()[1]


@pytest.mark.parametrize("case", ["port in use", "port 99999", "[::]", "a non-local address",
                                  "a non-local address, remote allowed", "--log at a directory",
                                  "--log at a read-only place", "--idle-timeout 0"])
def test_serve_errors_are_one_line(case, busy_port, tmp_path):
    argv, token, expected = {
        "port in use": (["--link", f"socket://127.0.0.1:{busy_port}"], None, f"port {busy_port} is in use"),
        "port 99999": (["--link", "socket://127.0.0.1:99999"], None, "the port must be 0..65535"),
        "[::]": (["--link", "socket://[::]:0"], None, "listens on every interface"),
        "a non-local address": (["--link", "socket://192.0.2.1:0"], None, "not a loopback address"),
        "a non-local address, remote allowed": (["--link", "socket://192.0.2.1:0", "--allow-remote"], TOKEN,
                                                "192.0.2.1 is not an address of this machine"),
        "--log at a directory": (["--link", "socket://127.0.0.1:0", "--log", tmp_path], None, "Is a directory"),
        # a read-only sysctl: not even root writes there
        "--log at a read-only place": (["--link", "socket://127.0.0.1:0", "--log", "/proc/sys/kernel/ostype"], None,
                                       "Permission denied"),
        "--idle-timeout 0": (["--link", "socket://127.0.0.1:0", "--idle-timeout", "0"], None,
                             "--idle-timeout must be a positive number of seconds"),
    }[case]
    # the system's refusal of the log's write is exit 3 (twin.exitcodes); a path that is no file is bad input, 2
    code = EXIT_IO if case == "--log at a read-only place" else EXIT_USAGE
    assert expected in _serve_error(*argv, token=token, code=code)


def test_serve_errors_through_the_cli(cli):
    assert cli("controller", "serve", "--leds", LEDS, "--link", "socket://127.0.0.1:99999") == (
        2, ["hemicube: error: --link socket://127.0.0.1:99999: the port must be 0..65535 (0: any free port)"])
    assert cli("controller", "serve", "--leds", LEDS, "--link", "socket://127.0.0.1:0", "--log",
               "/proc/sys/kernel/ostype") == (EXIT_IO, ["hemicube: error: --log /proc/sys/kernel/ostype: permission "
                                                        "denied; choose a folder you may write to"])


def test_the_capture_proves_it_holds_the_token(monkeypatch, cli, tmp_path):
    """The capture's own client (the hardware backend's controller link) does the handshake, with the token
    from the environment; without it, the capture stops in one line before anything is written."""
    import twin
    from twin.capture.backends.hardware import open_hardware

    rig = twin.load_rig("mini")
    levels = np.full((rig.num_leds, 3), 7, np.uint8)
    proc, url = spawn(rig.num_leds, token=TOKEN)
    try:
        monkeypatch.delenv(TOKEN_ENV, raising=False)
        rc, err = cli("capture", "--rig", "mini", "--sample", "ramps", "--backend", "hardware", "--led", url,
                      "--cameras", "emulated", "--no-progress", "-o", tmp_path / "cap")
        assert (rc, err) == (2, [f"hemicube: error: LED controller at {url} asks for a token: set {TOKEN_ENV} to "
                                 "the token it was started with"])
        assert not (tmp_path / "cap").exists()
        monkeypatch.setenv(TOKEN_ENV, TOKEN)
        with open_hardware(rig, None, seed=1, led=url, cameras="emulated") as backends:
            assert backends["sample"].show(levels) == {"led_crc": f"{crc32(levels.tobytes()):08x}"}
    finally:
        _stop(proc)
