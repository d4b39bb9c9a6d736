"""Start `silcr` components as subprocesses for the cross-process benchmarks."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

import zenoh

from common.zenoh_session import open_session, session_config


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
        p = subprocess.Popen([sys.executable, "-m", "common.cli", *args, *extra], stdout=log, stderr=subprocess.STDOUT)
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


class LatestStats:
    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self.latest: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.latest[str(sample.key_expr)] = json.loads(sample.payload.to_bytes())

    def get(self, key: str) -> dict[str, Any]:
        with self._lock:
            return dict(self.latest.get(key, {}))


def wait_until(pred: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    raise TimeoutError(f"timed out waiting for {what}")
