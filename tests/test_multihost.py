"""Across hosts on one machine: Linux network namespaces joined by veth links.

`hub` runs the router, the buffer service and the learner; actors run in two
other namespaces with their own addresses and reach the hub only through their
veth link, as on separate machines. The test process watches from the root
namespace through a third link. Then one actor's link is cut for longer than
Zenoh's lease and brought back: the actor must reconnect and go on publishing.
"""

from __future__ import annotations

import signal
import subprocess
import time

import pytest

from silcr.bench.netns import Namespaces, why_not_namespaces
from silcr.common import protocol as P
from tests.helpers import LatestJson, Processes, client_when_up, free_port, small_run_config, wait_for

pytestmark = pytest.mark.skipif(bool(why_not_namespaces()), reason=str(why_not_namespaces()))


def test_actors_on_other_hosts_train_and_survive_a_network_cut(tmp_path):
    run = "multihost"
    keys = P.Keys(run)
    port = free_port()
    small = small_run_config(tmp_path)
    procs = Processes(tmp_path)

    def start(name: str, ns: str, *args: str):
        procs.start(name, *args, netns=ns)

    session = None
    with Namespaces(hosts=2) as nets:
        nets.a1, nets.a2 = nets.hosts
        try:
            start("router", nets.hub, "router", "--listen", f"tcp/0.0.0.0:{port}")
            local = ["--run", run, "--config", str(small), "--connect", f"tcp/127.0.0.1:{port}"]
            start("buffer", nets.hub, "buffer", *local)
            start("learner", nets.hub, "learner", *local, "--runs-dir", str(tmp_path / "runs"))
            for i, ns in ((1, nets.a1), (2, nets.a2)):
                start(f"actor-{i}", ns, "actor", "--run", run, "--config", str(small),
                      "--actor-id", str(i), "--zenoh-mode", "client", "--connect", f"tcp/{nets.addr(i, 1)}:{port}")

            session = client_when_up(port, host=nets.addr(0, 1))
            stats = LatestJson(session, keys.stats_all)

            def check_alive():
                dead = [n for n, p in procs.procs.items() if p.poll() is not None]
                assert not dead, f"{dead} exited: {procs.log(dead[0])[-1500:]}"

            def actor(i):
                check_alive()
                return stats.get(keys.stats_actor(i)) or {}

            def learner():
                check_alive()
                return stats.get(keys.stats_learner) or {}

            def buffer():
                check_alive()
                return stats.get(keys.stats_buffer) or {}

            # Episodes cross from both actor hosts, weights come back, training advances.
            wait_for(lambda: learner().get("updates", 0) > 30, 180, "training with actors on two other hosts")
            wait_for(lambda: actor(1).get("policy_version", -1) > 0 and actor(2).get("policy_version", -1) > 0, 60,
                     "learner weights to reach both actor hosts")
            buf = stats.get(keys.stats_buffer)
            assert buf["actors_alive"] == 2 and buf["episodes_rejected"] == 0

            # Cut actor 1's host off for longer than the Zenoh lease (10 s), then reconnect it.
            a1_link = nets.link_name("x", 1)
            subprocess.run(["ip", "-n", nets.a1, "link", "set", a1_link, "down"], check=True)
            time.sleep(3)
            frozen = actor(1).get("episodes", 0)
            t_cut = time.monotonic()
            wait_for(lambda: buffer().get("actors_alive") == 1, 90,
                     "the buffer to notice the lost actor")
            print(f"the buffer noticed the cut after {time.monotonic() - t_cut + 3:.1f}s")
            assert actor(1).get("episodes", 0) == frozen  # nothing arrives from the cut-off host
            u = learner()["updates"]
            wait_for(lambda: learner()["updates"] > u + 10, 60, "training to go on with the other actor")
            time.sleep(2)
            subprocess.run(["ip", "-n", nets.a1, "link", "set", a1_link, "up"], check=True)
            # While the link is down the router blocks up to 5 s on each message for the dead link, serving no one
            # meanwhile: the learner gets no batches and actor 2 hears no pause. Now and then actor 2 runs far ahead
            # of the learner so, and once the router is free the rate limiter pauses every actor until the learner
            # has caught up (3 of 4 actors cut: once 42,682 transitions against 1,927 updates, about 3 minutes at
            # 215 updates/s here). That, not a stuck actor, is what stop 68's CI timed out on (below).
            t_up = time.monotonic()
            # Up to 8 minutes: in the CI run of this change the whole test took 246 s on an idle machine.
            wait_for(lambda: not buffer().get("actors_paused", True), 480,
                     "the learner to catch up with what actor 2 stored during the cut (the rate limiter's pause)")
            print(f"actors unpaused {time.monotonic() - t_up:.1f}s after the link came back")
            # Published again: the buffer confirms every episode actor 1 finished before the cut and one more after
            # it (confirmations are cumulative in its order): at most one 1,000-step episode once the policy
            # balances the pendulum.
            wait_for(lambda: actor(1).get("episodes_written", 0) > frozen, 120, "actor 1 to reconnect and publish again")
            wait_for(lambda: buffer().get("actors_alive") == 2, 60,
                     "the buffer to see actor 1 again")
            v = actor(1).get("policy_version", 0)
            wait_for(lambda: actor(1).get("policy_version", 0) > v, 60, "new weights to reach actor 1 again")
            assert procs.procs["actor-1"].poll() is None  # the same process, reconnected
            # It said so: the lost link, then its return with the outage's length.
            a1_log = procs.log("actor-1")
            lost = a1_log.find("WARNING actor 1 lost its last Zenoh link")
            assert 0 <= lost < a1_log.find("actor 1 linked again after", lost), a1_log[-2000:]
            assert "lost its last Zenoh link" not in procs.log("actor-2")
            assert stats.get(keys.stats_buffer)["episodes_rejected"] == 0
        except AssertionError as e:
            # Twice (a loaded full suite, then an idle CI) actor 1 linked again but did not finish four more episodes
            # within 120 s; cuts repeated here showed why (above): every actor paused while the learner caught up.
            # Keep what each side said, the last stats seen and where each of actor 1's threads was (SIGUSR1:
            # common/lifecycle.py), to tell a rate-limited actor from a stuck one if it fails again.
            if procs.procs["actor-1"].poll() is None:
                procs.procs["actor-1"].send_signal(signal.SIGUSR1)
                time.sleep(1.0)
            seen = {k: stats.get(k) for k in (keys.stats_actor(1), keys.stats_learner)} if session is not None else None
            logs = "".join(f"\n--- {n}.log ---\n{procs.log(n)[-chars:]}"
                           for n, chars in (("actor-1", 12000), ("router", 1500), ("buffer", 1500)))
            raise AssertionError(f"{e}\nthe last stats seen of actor 1 and the learner: {seen}{logs}") from None
        finally:
            if session is not None:  # left open, a session whose router is gone can hang the interpreter's exit
                session.close()
            procs.stop_all()
    assert procs.orphans == []