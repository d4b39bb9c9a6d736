"""Start `silcr` components as subprocesses for the cross-process benchmarks."""

from __future__ import annotations

import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import zenoh

from silcr.common.commands import command
from silcr.common.zenoh_session import open_session, session_config


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Components:
    def __init__(self) -> None:
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.dir = Path(tempfile.mkdtemp(prefix="silcr-bench-"))
        self.procs: list[subprocess.Popen] = []

    def start(self, *args: str) -> subprocess.Popen:
        log = open(self.dir / f"{len(self.procs)}-{args[0]}.log", "w")
        extra = ["--listen", self.endpoint] if args[0] == "router" else ["--connect", self.endpoint]
        p = subprocess.Popen(command(*args, *extra), stdout=log, stderr=subprocess.STDOUT)
        self.procs.append(p)
        return p

    def session(self) -> zenoh.Session:
        deadline = time.monotonic() + 30
        while True:
            try:
                return open_session(session_config([self.endpoint], [], "peer"))
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def stop(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()


def wait_until(pred: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    raise TimeoutError(f"timed out waiting for {what}")
