"""Loopback helpers the tests share: free UDP ports on 127.0.0.1 (one, or a block of consecutive
ones), and ``python -m swarmplan`` of this checkout as a subprocess: its environment, a run with
captured output, a start with output into a log file, and a clean stop (a signal, then SIGKILL).

Reached from every test folder as ``import loopback`` (tests/conftest.py puts tests/ on the path).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HOST = "127.0.0.1"


def free_udp_port(host: str = HOST) -> int:
    """A UDP port free on ``host`` right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def bind_port_block(count: int, host: str = HOST, tries: int = 50) -> list[socket.socket]:
    """``count`` UDP sockets bound to consecutive free ports (the first one's port is the base);
    the caller closes them."""
    for _ in range(tries):
        base = free_udp_port(host)
        if base + count > 65535:
            continue
        socks: list[socket.socket] = []
        try:
            for k in range(count):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind((host, base + k))
            return socks
        except OSError:
            for s in socks:
                s.close()
    raise RuntimeError(f"no block of {count} free UDP ports on {host}")


def free_port_block(count: int, host: str = HOST) -> int:
    """A base port with ``count`` consecutive UDP ports free on ``host`` right now (found bound,
    then released for the test's own sockets or processes to bind)."""
    socks = bind_port_block(count, host)
    base = socks[0].getsockname()[1]
    for s in socks:
        s.close()
    return base


def env(**extra: str) -> dict[str, str]:
    """The environment of a ``swarmplan`` subprocess: this checkout on PYTHONPATH, MAVLink 2, no
    signing key from the caller's shell; ``extra`` on top."""
    out = dict(os.environ, PYTHONPATH=str(REPO), MAVLINK20="1")
    out.pop("SWARMPLAN_SIGNING_KEY", None)
    out.update(extra)
    return out


def run_swarmplan(
    args: list[str], timeout: float, environ: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """``python -m swarmplan ARGS`` to its end (killed at ``timeout``), output captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "swarmplan", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env() if environ is None else environ,
        cwd=REPO,
    )


def start_swarmplan(
    args: list[str],
    log: Path,
    environ: dict[str, str] | None = None,
    *,
    stdout_pipe: bool = False,
) -> subprocess.Popen:
    """``python -m swarmplan ARGS`` started, stdout and stderr appended to ``log`` (with
    ``stdout_pipe``: only stderr, stdout a pipe to read). End it with :func:`stop`."""
    with open(log, "ab") as sink:
        return subprocess.Popen(
            [sys.executable, "-m", "swarmplan", *args],
            stdout=subprocess.PIPE if stdout_pipe else sink,
            stderr=sink if stdout_pipe else subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env() if environ is None else environ,
            cwd=REPO,
        )


def stop(proc: subprocess.Popen, timeout_s: float = 5.0, sig: int = signal.SIGTERM) -> int | None:
    """End ``proc`` (``sig``, then SIGKILL after ``timeout_s``) and return its exit status."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    return proc.returncode


def run_swarmplan_on_terminal(args: list[str], timeout: float) -> tuple[int, str, str]:
    """``python -m swarmplan ARGS`` with its stderr a terminal (a pty, as in a user's shell):
    (exit status, stdout, everything written to the terminal). The terminal is read while the
    process runs: what is left in it when the process closes it may be lost. The terminal is
    24 x 100 (a terminal of width 0 gets no progress bar from tqdm)."""
    import fcntl
    import pty
    import struct
    import termios
    import threading

    controller, terminal = pty.openpty()
    fcntl.ioctl(terminal, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    shown: list[bytes] = []

    def read() -> None:
        while True:
            try:
                chunk = os.read(controller, 65536)
            except OSError:  # the process closed the terminal
                return
            if not chunk:
                return
            shown.append(chunk)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    proc = subprocess.Popen(
        [sys.executable, "-m", "swarmplan", *args],
        stdout=subprocess.PIPE,
        stderr=terminal,
        stdin=subprocess.DEVNULL,
        env=env(),
        cwd=REPO,
    )
    os.close(terminal)
    try:
        out, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        reader.join(5)
        os.close(controller)
    return proc.returncode, out.decode(errors="replace"), b"".join(shown).decode(errors="replace")
