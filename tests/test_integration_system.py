"""Router, buffer, learner and actors as separate processes over real Zenoh."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
import zenoh

from silcr.common import protocol as P
from tests.helpers import REPO, LatestJson, Processes, client_when_up, free_port, wait_for

RUN = "itest-system"
KEYS = P.Keys(RUN)
COMMON = ["--run", RUN, "--env", "InvertedPendulum-v5", "--stats-interval", "0.2"]
NETS = ["--hidden", "16", "16"]


@pytest.fixture(scope="module")
def system(tmp_path_factory):
    port = free_port()
    logs = tmp_path_factory.mktemp("system-logs")
    procs = Processes(logs)
    ep = f"tcp/127.0.0.1:{port}"
    procs.start("router", "router", "--listen", ep)
    procs.start("buffer", "buffer", *COMMON, "--connect", ep, "--learning-starts", "300", "--spi-tolerance", "200")
    procs.start(
        "learner", "learner", *COMMON, *NETS, "--connect", ep, "--runs-dir", str(logs / "runs"), "--learning-starts", "300",
        "--batch-size", "32", "--weights-interval", "5", "--eval-episodes", "1", "--eval-interval", "1000000",
        "--total-steps", "1000000000", "--torch-threads", "1",
    )
    procs.start("actor-0", "actor", *COMMON, *NETS, "--connect", ep, "--actor-id", "0", "--weights-poll-steps", "5")
    session = client_when_up(port)
    stats = LatestJson(session, KEYS.stats_all)
    yield procs, session, stats, ep
    session.close()
    procs.stop_all()


def _learner(stats):
    return stats.get(KEYS.stats_learner) or {}


def test_weights_reach_actor_with_increasing_versions(system):
    procs, _, stats, _ = system
    key = KEYS.stats_actor(0)
    wait_for(lambda: (stats.get(key) or {}).get("policy_version", -1) >= 3, 120,
             f"actor 0 to get policy version 3\n{procs.log('learner')[-2000:]}")
    v1 = stats.get(key)["policy_version"]
    wait_for(lambda: stats.get(key)["policy_version"] > v1, 60, "a newer policy version at the actor")
    versions = [m["policy_version"] for m in stats.history[key]]
    assert versions == sorted(versions)
    assert _learner(stats)["updates"] > 0


def test_late_joining_actor_gets_weights_at_once(system):
    procs, _, stats, ep = system
    current = _learner(stats)["policy_version"]
    assert current >= 3
    procs.start("actor-1", "actor", *COMMON, *NETS, "--connect", ep, "--actor-id", "1", "--weights-poll-steps", "1000000")
    first = wait_for(lambda: stats.first.get(KEYS.stats_actor(1)), 60, "actor 1's first stats")
    # weights_poll_steps is huge, so only the start-up query can have given it a learner version
    assert first["policy_version"] >= current


def test_bad_episodes_are_rejected_while_training_goes_on(system):
    _, session, stats, _ = system
    before = _learner(stats)["updates"]
    pub = session.declare_publisher(KEYS.episodes, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_for(lambda: pub.matching_status.matching, 10, "the buffer")
    for payload in (b"\x00\x01", b"", P.ShutdownNotice("x").encode()):
        pub.put(payload)
    wait_for(lambda: (stats.get(KEYS.stats_buffer) or {}).get("episodes_rejected", 0) >= 3, 20, "3 rejections")
    wait_for(lambda: _learner(stats)["updates"] > before + 20, 60, "training to go on")


def test_liveliness_tokens(system):
    _, session, _, _ = system
    alive = {str(r.ok.key_expr) for r in session.liveliness().get(f"{KEYS.prefix}/alive/**", timeout=3) if r.ok}
    assert {KEYS.alive("buffer"), KEYS.alive("learner"), KEYS.alive("actor", 0), KEYS.alive("actor", 1)} <= alive


def test_actors_leaving_and_joining_never_deadlocks(system):
    procs, _, stats, ep = system
    for name in ("actor-0", "actor-1"):
        procs.procs[name].send_signal(signal.SIGKILL)
        procs.procs[name].wait(10)
    wait_for(lambda: (stats.get(KEYS.stats_buffer) or {}).get("actors_alive") == 0, 20, "the buffer to see the actors leave")
    # Without actors the learner uses up its samples-per-insert allowance and waits.
    def plateau():
        a = _learner(stats)["updates"]
        import time
        time.sleep(1.5)
        return _learner(stats)["updates"] == a and a
    stalled_at = wait_for(plateau, 60, "the learner to wait for data")
    assert procs.procs["learner"].poll() is None and procs.procs["buffer"].poll() is None
    procs.start("actor-2", "actor", *COMMON, *NETS, "--connect", ep, "--actor-id", "2")
    wait_for(lambda: _learner(stats)["updates"] > stalled_at + 20, 90, "training to resume with a new actor")


def test_sigterm_stops_every_component_cleanly(system):
    procs, _, _, _ = system
    for name, p in procs.procs.items():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for name, p in procs.procs.items():
        if name in ("actor-0", "actor-1"):
            continue  # killed above
        assert p.wait(30) == 0, f"{name} exited with {p.returncode}:\n{procs.log(name)[-2000:]}"
    assert os.path.exists  # nothing left running is checked by the fixture's stop_all


def test_an_actor_with_no_buffer_waits_awake_and_says_so(tmp_path):
    """With no buffer service listening an actor takes no steps (an episode it finished would have nowhere to
    go), yet goes on publishing its stats, `waiting_for_buffer` true; once a buffer is there it steps and
    its episodes arrive. Before, it stepped to its first episode's end and blocked there, publishing nothing."""
    port = free_port()
    procs = Processes(tmp_path)
    ep = f"tcp/127.0.0.1:{port}"
    run = "itest-no-buffer"
    common = ["--run", run, "--env", "InvertedPendulum-v5", "--stats-interval", "0.2"]
    keys = P.Keys(run)
    procs.start("router", "router", "--listen", ep)
    procs.start("actor-0", "actor", *common, *NETS, "--connect", ep, "--actor-id", "0", "--weights-wait", "0")
    session = client_when_up(port)
    try:
        stats = LatestJson(session, keys.stats_all)
        actor = keys.stats_actor(0)
        wait_for(lambda: len([m for m in stats.history.get(actor, []) if m.get("waiting_for_buffer")]) >= 5, 60,
                 f"actor stats saying it waits for the buffer\n{procs.log('actor-0')[-2000:]}")
        assert stats.get(actor)["steps"] == 0 and stats.get(actor)["waited_for_buffer_s"] > 0
        mon = subprocess.run([sys.executable, "-m", "silcr.cli", "monitor", "--run", run, "--connect", ep, "--once",
                              "--timeout", "2"], capture_output=True, text=True, timeout=60, cwd=REPO,
                             env={**os.environ, "COLUMNS": "200"})
        assert mon.returncode == 0 and "waiting for the buffer" in mon.stdout, mon.stdout + mon.stderr
        procs.start("buffer", "buffer", *common, "--connect", ep)
        wait_for(lambda: (stats.get(keys.stats_buffer) or {}).get("episodes_received", 0) > 0, 60,
                 f"episodes at the buffer\n{procs.log('actor-0')[-2000:]}")
        wait_for(lambda: stats.get(actor)["steps"] > 0 and stats.get(actor)["waiting_for_buffer"] is False, 30,
                 "the actor's stats to say it steps")
    finally:
        session.close()
        procs.stop_all()
    assert procs.orphans == []
