"""Real processes and real Zenoh sessions for the integration tests."""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable

import zenoh

from silcr.common import protocol as P

REPO = Path(__file__).resolve().parent.parent


SMALL_RUN_TOML = """env = "InvertedPendulum-v5"
hidden = [32, 32]
learning_starts = 300
batch_size = 32
eval_episodes = 1
stats_interval = 0.3
spi_tolerance = 300
total_steps = 100000000
"""


#: The options of a small run that ends (a few thousand steps of InvertedPendulum-v5, the env and the budget given
#: elsewhere), for the deployments' tests (compose, Slurm): checkpoints and stats often enough to watch.
SMALL_FINITE_RUN_TOML = """hidden = [32, 32]
learning_starts = 500
expert_capacity = 1000
batch_size = 64
eval_interval = 1000
eval_episodes = 2
checkpoint_interval = 300
buffer_checkpoint_interval = 5
stats_interval = 0.5
spi_tolerance = 300
torch_threads = 1
"""


def small_run_config(directory: Path) -> Path:
    """A TOML file of options for a small, endless run, usable by every component (each reads its own options)."""
    path = directory / "small.toml"
    path.write_text(SMALL_RUN_TOML)
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(pred: Callable[[], Any], timeout: float, what: str, interval: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f}s waiting for {what}")


class Processes:
    """`silcr` subprocesses tagged through their environment, so leftovers can be found."""

    def __init__(self, log_dir: Path) -> None:
        self.tag = uuid.uuid4().hex
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}
        self.orphans: list[int] = []

    def env(self) -> dict[str, str]:
        # SILCR_RUNS_DIR: checkpoints of components started without --runs-dir stay out of the repository.
        return {**os.environ, "SILCR_TEST_TAG": self.tag, "PYTHONUNBUFFERED": "1",
                "SILCR_RUNS_DIR": str(self.log_dir / "runs")}

    def start(self, name: str, *args: str, new_session: bool = False, sigint_ignored: bool = False,
              netns: str | None = None) -> subprocess.Popen:
        """`sigint_ignored`: start it as a shell starts a background job, with SIGINT ignored (inherited); `netns`:
        in that network namespace (a host of `bench.netns.Namespaces`)."""
        log = open(self.log_dir / f"{name}.log", "w")
        command = [sys.executable, "-m", "silcr.cli", *args]
        if netns is not None:
            command = ["ip", "netns", "exec", netns, *command]
        if sigint_ignored:  # the shell's way: an ignored disposition survives exec
            command = ["sh", "-c", "trap '' INT; exec \"$@\"", "sh", *command]
        p = subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, env=self.env(), cwd=REPO, start_new_session=new_session,
        )
        self.procs[name] = p
        return p

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text(errors="replace")

    def stop_all(self, grace_s: float = 5.0) -> None:
        """SIGTERM what is still running, then give every tagged process `grace_s` to exit by itself.

        What is still alive after that was left behind (an orphan): it is recorded in
        `orphans`, for the tests to assert on, and killed.
        """
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.procs.values():
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        deadline = time.monotonic() + grace_s
        while (left := tagged_pids(self.tag)) and time.monotonic() < deadline:
            time.sleep(0.1)
        self.orphans = left
        for pid in left:
            os.kill(pid, signal.SIGKILL)


def train_to_the_end(tmp_path: Path, run: str, *args: str) -> tuple[list[dict[str, str]], "Processes"]:
    """`silcr train --run RUN --runs-dir tmp/runs ARGS` to its end (10 minutes at most): its progress.csv rows."""
    procs = Processes(tmp_path)
    train = procs.start("train", "train", "--run", run, "--runs-dir", str(tmp_path / "runs"), *args)
    try:
        assert train.wait(600) == 0, procs.log("train")
    finally:
        procs.stop_all()
    return list(csv.DictReader(open(tmp_path / "runs" / run / "progress.csv"))), procs


def tagged_pids(tag: str) -> list[int]:
    """Live processes whose environment carries SILCR_TEST_TAG=tag (zombies excluded)."""
    found = []
    needle = f"SILCR_TEST_TAG={tag}".encode()
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            if needle in (d / "environ").read_bytes().split(b"\0"):
                state = (d / "stat").read_text().rsplit(")", 1)[1].split()[0]
                if state != "Z":
                    found.append(int(d.name))
        except OSError:
            continue
    return found


def client_session(port: int, host: str = "127.0.0.1") -> zenoh.Session:
    """A plain Zenoh client built here, not by the project: what an outside tool would open."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/{host}:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(conf)


def client_when_up(port: int, timeout: float = 60, host: str = "127.0.0.1") -> zenoh.Session:
    """A `client_session` once the router on `port` accepts it."""
    def attempt() -> zenoh.Session | None:
        try:
            return client_session(port, host)
        except zenoh.ZError:
            return None

    return wait_for(attempt, timeout, f"the router on port {port}")


class LatestJson:
    """Latest JSON message per key under a key expression."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self._lock = threading.Lock()
        self.latest: dict[str, dict] = {}
        self.first: dict[str, dict] = {}
        self.history: dict[str, list[dict]] = {}
        self.encodings: dict[str, str] = {}
        session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        data = json.loads(sample.payload.to_bytes())
        with self._lock:
            key = str(sample.key_expr)
            self.latest[key] = data
            self.first.setdefault(key, data)
            self.history.setdefault(key, []).append(data)
            self.encodings[str(sample.key_expr)] = str(sample.encoding)

    def get(self, key: str) -> dict | None:
        with self._lock:
            return self.latest.get(key)


def two_batch_reply(obs_dim: int, act_dim: int) -> P.BatchReply:
    """A buffer reply of 2 batches of 2 plain rows, for driving `Update.train` directly."""
    batch = P.Batch.empty(4, obs_dim, act_dim)
    batch.obs[:] = batch.next_obs[:] = 0.1
    batch.actions[:] = 0.0
    batch.rewards[:] = 1.0
    batch.terminated[:] = batch.truncated[:] = 0
    batch.policy_version[:] = 0
    return P.BatchReply("ok", {"batches": 2, "batch_size": 2}, batch)
