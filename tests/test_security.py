"""TLS with mutual authentication and access control on the router (deploy/zenoh/*.json5).

Real processes: a TLS-only router with the shipped access-control template, and
buffer, learner and actor in client mode, each with its own certificate from
deploy/make-certs.sh. Training must advance through it, and a rogue client that
holds an actor's credentials must be unable to publish weights or read stats, and
clients without a certificate must be refused.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time

import pytest
import zenoh

from silcr.common import protocol as P
from tests.helpers import REPO, LatestJson, Processes, free_port, small_run_config, wait_for

def _render(template: str, out, **values: str):
    text = (REPO / "deploy" / "zenoh" / template).read_text()
    for k, v in values.items():
        text = text.replace(k, v)
    out.write_text(text)
    return out


def _tls_client(port: int, certs, role: str | None) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    tls = {"root_ca_certificate": str(certs / "ca.pem")}
    if role:
        tls |= {"connect_certificate": str(certs / f"{role}.pem"), "connect_private_key": str(certs / f"{role}.key"),
                "enable_mtls": True}
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    return zenoh.open(conf)


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    d = tmp_path_factory.mktemp("certs")
    subprocess.run([str(REPO / "deploy" / "make-certs.sh"), str(d), "127.0.0.1", "localhost"], check=True,
                   capture_output=True, timeout=120)
    return d


def test_tls_acl_lets_the_run_train_and_refuses_a_rogue_actor(tmp_path, certs):
    run = "secure"
    keys = P.Keys(run)
    port = free_port()
    procs = Processes(tmp_path)
    router_conf = _render("router-tls-acl.json5", tmp_path / "router.json5", CERTS=str(certs), RUN=run)
    procs.start("router", "router", "--listen", f"tls/127.0.0.1:{port}", "--zenoh-config", str(router_conf))
    small = small_run_config(tmp_path)
    common = ["--run", run, "--zenoh-mode", "client", "--connect", f"tls/127.0.0.1:{port}", "--config", str(small)]
    for role in ("buffer", "learner", "actor"):
        conf = _render("client-tls.json5", tmp_path / f"{role}.json5", CERTS=str(certs), ROLE=role)
        extra = ["--runs-dir", str(tmp_path / "runs")] if role != "actor" else []
        procs.start(role, role, *common, *extra, "--zenoh-config", str(conf),
                    "--health-file", str(tmp_path / f"{role}.health.json"))
    try:
        monitor = wait_for(lambda: _try(lambda: _tls_client(port, certs, "monitor")), 60, "the TLS router")
        stats = LatestJson(monitor, keys.stats_all)
        weights_seen: list[bytes] = []
        lock = threading.Lock()

        def on_weights(s: zenoh.Sample) -> None:
            with lock:
                weights_seen.append(s.payload.to_bytes())

        monitor.declare_subscriber(keys.weights, on_weights)
        def advancing():
            dead = [n for n, p in procs.procs.items() if p.poll() is not None]
            assert not dead, f"{dead} exited: {procs.log(dead[0])[-1500:]}"
            return (stats.get(keys.stats_learner) or {}).get("updates", 0) > 20

        wait_for(advancing, 180, "training to advance over TLS with access control")
        buf = stats.get(keys.stats_buffer)
        assert buf["episodes_received"] > 0 and buf["episodes_rejected"] == 0

        # The readiness probe through the same TLS link and access control, with each role's own certificate
        # (as the Kubernetes TLS overlay runs it): an actor may ask for its own liveliness token.
        from silcr.cli import command

        for role in ("buffer", "learner", "actor"):
            r = subprocess.run(command("health", "--ready", "--health-file", str(tmp_path / f"{role}.health.json"),
                                       "--zenoh-mode", "client", "--connect", f"tls/127.0.0.1:{port}",
                                       "--zenoh-config", str(tmp_path / f"{role}.json5")),
                               capture_output=True, text=True, timeout=60)
            assert r.returncode == 0 and "visible" in r.stdout, (role, r.stdout + r.stderr)

        # A rogue client with an actor's (valid) credentials.
        rogue = _tls_client(port, certs, "actor")
        peeked: list[str] = []
        rogue.declare_subscriber(f"{keys.prefix}/stats/**", lambda s: peeked.append(str(s.key_expr)))
        rogue.declare_subscriber("silcr/other-run/**", lambda s: peeked.append(str(s.key_expr)))
        time.sleep(1.0)
        for _ in range(5):
            rogue.put(keys.weights, b"rogue weights")
            rogue.put(keys.control_shutdown, P.ShutdownNotice("rogue").encode())
        time.sleep(2.0)  # stats arrive every 0.3 s: a permitted subscriber would have seen several
        with lock:
            assert weights_seen and b"rogue weights" not in weights_seen
        assert peeked == []
        # Its shutdown message was dropped too: the run is still training.
        u = stats.get(keys.stats_learner)["updates"]
        wait_for(lambda: stats.get(keys.stats_learner)["updates"] > u + 10, 60, "training to go on")
        assert all(p.poll() is None for p in procs.procs.values())
        rogue.close()
        monitor.close()

        # No certificate, or plain TCP: refused at connection time.
        with pytest.raises(zenoh.ZError):
            _tls_client(port, certs, None).close()
        plain = zenoh.Config()
        plain.insert_json5("mode", '"client"')
        plain.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        plain.insert_json5("scouting/multicast/enabled", "false")
        with pytest.raises(zenoh.ZError):
            zenoh.open(plain).close()
    finally:
        procs.stop_all()
    assert procs.orphans == []
def _try(make):
    try:
        return make()
    except zenoh.ZError:
        return None
