"""`silcr health` (issue 39): the probes Kubernetes runs. Alive means the component's main loop still writes
its heartbeat (a stuck one stops it, a slow one only delays it); ready means its Zenoh liveliness token is
visible through the router. Real components over real Zenoh, stopped with SIGSTOP to be stuck."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest

from silcr.cli import command
from silcr.common import health
from tests.helpers import Processes, free_port, wait_for

RUN = "probed"
COMMON = ["--run", RUN, "--env", "InvertedPendulum-v5", "--stats-interval", "0.5", "--zenoh-mode", "client"]
NETS = ["--hidden", "16", "16"]


def test_a_heartbeat_is_alive_until_it_is_stale(tmp_path):
    path = tmp_path / "beat.json"
    with pytest.raises(ValueError, match="no heartbeat"):
        health.alive(path, 10)
    beat = health.Heartbeat(path, "r", "buffer", "silcr/r/alive/buffer")
    beat.beat()
    assert "buffer of run r" in health.alive(path, 10)
    t = json.loads(path.read_text())["time"]
    with pytest.raises(ValueError, match="stuck"):
        health.alive(path, 10, now=t + 11)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="unreadable"):
        health.alive(path, 10)
    assert not (tmp_path / "beat.json.tmp").exists()


def _probe(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(command("health", *args), capture_output=True, text=True, timeout=60)


@pytest.mark.slow
def test_the_probes_tell_a_stuck_component_from_a_running_one_and_a_joined_one_from_a_lost_one(tmp_path):
    procs = Processes(tmp_path)
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    files = {name: tmp_path / f"{name}.health.json" for name in ("buffer", "learner", "actor")}
    router = procs.start("router", "router", "--listen", ep)
    buffer = procs.start("buffer", "buffer", *COMMON, "--connect", ep, "--learning-starts", "300",
                         "--health-file", str(files["buffer"]))
    procs.start("learner", "learner", *COMMON, *NETS, "--connect", ep, "--learning-starts", "300", "--batch-size", "32",
                "--eval-episodes", "1", "--total-steps", "100000000", "--torch-threads", "1",
                "--health-file", str(files["learner"]))
    procs.start("actor", "actor", *COMMON, *NETS, "--connect", ep, "--actor-id", "-1", "--health-file", str(files["actor"]))
    link = ["--connect", ep, "--zenoh-mode", "client"]
    try:
        for name, path in files.items():
            wait_for(path.exists, 120, f"the {name}'s first heartbeat")
            r = _probe("--health-file", str(path), "--ready", *link)
            assert r.returncode == 0 and "ok" in r.stdout and "visible" in r.stdout, r.stdout + r.stderr
        actor_token = json.loads(files["actor"].read_text())["token"]
        assert actor_token.startswith(f"silcr/{RUN}/alive/actor/")  # the random id it picked
        # where a component is: SIGUSR1 prints every thread's stack to its log, and it goes on
        actor = procs.procs["actor"]
        actor.send_signal(signal.SIGUSR1)
        wait_for(lambda: "in run_actor" in procs.log("actor"), 30, "the actor's stacks in its log")
        assert "Current thread" in procs.log("actor") or "Thread 0x" in procs.log("actor")
        beat = json.loads(files["actor"].read_text())["time"]
        wait_for(lambda: json.loads(files["actor"].read_text())["time"] > beat, 30, "the actor's next heartbeat")
        assert actor.poll() is None
        # a stuck buffer: its process stopped, its heartbeat ages; a liveness probe says so, and then it is fine again
        buffer.send_signal(signal.SIGSTOP)
        time.sleep(3)
        r = _probe("--health-file", str(files["buffer"]), "--stale-after", "2")
        assert r.returncode == 1 and "stuck" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        buffer.send_signal(signal.SIGCONT)
        wait_for(lambda: _probe("--health-file", str(files["buffer"]), "--stale-after", "2").returncode == 0, 30,
                 "the buffer's heartbeat again")
        # slow is not stuck: the default threshold leaves a component minutes
        assert _probe("--health-file", str(files["learner"])).returncode == 0
        # the router gone: alive, but not ready (the token is not visible), one line saying so
        router.send_signal(signal.SIGKILL)
        router.wait(10)
        r = _probe("--health-file", str(files["actor"]), "--ready", *link, "--timeout", "2")
        assert r.returncode == 1 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert _probe("--health-file", str(files["actor"])).returncode == 0
    finally:
        procs.stop_all()
    assert procs.orphans == []
    r = _probe("--health-file", str(tmp_path / "missing.json"))
    assert r.returncode == 1 and "no heartbeat" in r.stderr
