"""`silcr bench scale`: a real `silcr train` at several actor counts, measured from outside while it runs.

For each count it starts `silcr train --actors N --no-throttle` (the actors run at full speed
instead of at the learner's pace, so the traffic is what that many actors make), or with
`--paced` a plain `silcr train` (the actors at the learner's pace, as in a real run: on a
machine with fewer cores than actors, the only way the learner gets a core), waits
for the learner's first update,
then measures for a fixed window, and stops the run with SIGINT (the Ctrl-C path). What
it reports, per count (issue 20):

* episodes published (the actors' `episodes_written`), received, rejected, and lost:
  `episodes_missing` (gaps in an actor's sequence numbers, so any episode lost between
  two that arrived is counted) and `episodes_dropped` (left in the buffer's inbox at close);
* the weights' publication-to-use latency at the actors: the median of their medians,
  the largest of their 99th percentiles, and the worst actor's median;
* bytes per second of weights (each publication goes to every actor: `weights_bytes` x
  publications x actors) and of episodes (what the buffer received). Components are Zenoh
  peers, and gossip gives them direct links to each other (docs/performance.md), so
  these bytes leave the learner and reach the buffer without passing the router: the
  router's CPU share shows how little it carries;
* the router's, the buffer's, the learner's and the actors' CPU, in cores, from /proc;
* each actor process's resident memory (median and largest);
* the learner's duty cycle and updates per second.

Counts that would not fit in memory are refused by `silcr train` itself (one line, exit 2)
and reported as such. `--envs-per-actor` puts several envs in each actor process where
processes, not envs, are the limit.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from silcr.common.commands import command
from silcr.common import protocol as P
from silcr.common.zenoh_session import open_session, session_config
from silcr.deploy.monitor import StatsSnapshot

from .procs import Components, free_port, wait_until
from .timing import print_table, write_json

TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_seconds(pid: int) -> float | None:
    """A process's CPU time so far, all its threads, or None once it is gone.

    Read from the process's own CPU-time clock, exact to the nanosecond: /proc's utime and
    stime count 10 ms ticks, and a router relaying two actors uses about 2 ticks in a 5 s
    window, so a window could read 0. Linux names another process's clock
    ((~pid) << 3) | CPUCLOCK_SCHED (= 2), as glibc's clock_getcpuclockid does."""
    try:
        return time.clock_gettime(((~pid) << 3) | 2)
    except OSError:
        pass  # gone, or a clock this kernel does not give: /proc's ticks
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime
    except (OSError, IndexError, ValueError):
        return None


def rss_mb(pid: int) -> float | None:
    """A process's resident memory in MB (VmRSS), or None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _cpu_of(pids: dict[str, int]) -> dict[str, float | None]:
    return {name: _cpu_seconds(pid) for name, pid in pids.items()}


def measure(actors: int, seconds: float, env_id: str, envs_per_actor: int, hidden: list[int],
            weights_interval: int, first_update_s: float = 300.0, paced: bool = False,
            train_args: list[str] = ()) -> dict[str, Any]:
    """One `silcr train` with `actors` actors, measured for `seconds` after its first update."""
    run_name = f"bench-scale-{actors}-{int(time.time())}"
    keys = P.Keys(run_name)
    port = free_port()
    runs_dir = Path(tempfile.mkdtemp(prefix="silcr-bench-scale-"))
    log = open(runs_dir / "train.log", "w")
    proc = subprocess.Popen(
        command("train", "--run", run_name, "--runs-dir", str(runs_dir), "--env", env_id, "--actors", str(actors),
                "--envs-per-actor", str(envs_per_actor), "--hidden", *map(str, hidden), "--learning-starts", "2000",
                "--total-steps", str(10**9), "--eval-episodes", "0", "--stats-interval", "1",
                "--weights-interval", str(weights_interval), "--zenoh-listen", f"tcp/127.0.0.1:{port}",
                *([] if paced else ["--no-throttle"]), *train_args),
        stdout=log, stderr=subprocess.STDOUT,
    )
    comp = Components()
    comp.endpoint = f"tcp/127.0.0.1:{port}"
    result: dict[str, Any] = {"actors": actors, "envs_per_actor": envs_per_actor, "paced": paced,
                              "train_args": list(train_args)}
    try:
        try:
            wait_until(lambda: proc.poll() is not None or (runs_dir / run_name / "pids.json").exists(), 120,
                       "the run's pids")
        except TimeoutError:
            proc.poll()
        if proc.poll() is not None:
            return result | {"refused": (runs_dir / "train.log").read_text().strip().splitlines()[-1:]}
        with comp.session() as s:
            measured = _window(s, keys, actors, lambda: json.loads((runs_dir / run_name / "pids.json").read_text()),
                               seconds, first_update_s, paced)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # the Ctrl-C path: every component stops and checkpoints
        try:
            proc.wait(120)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        if proc.poll() is not None:
            shutil.rmtree(runs_dir, ignore_errors=True)  # the run's checkpoints; the numbers are in `measured`
    return result | measured


def measure_hosts(hosts: int, per_host: int, seconds: float, env_id: str, hidden: list[int], weights_interval: int,
                  first_update_s: float = 300.0, train_args: list[str] = ()) -> dict[str, Any]:
    """`hosts` network-namespace hosts of `per_host` actors each, around a hub (router, buffer, learner).

    Each host runs a Zenoh router of its own, linked to the hub's; its actors are clients of it.
    The learner's weights then cross each host's link once per publication and the host's router
    hands them to its actors (the relay per host of docs/scaling.md). The actors are paced by
    the learner. `train_args` go to the learner (`silcr learner` options)."""
    from .netns import Namespaces, why_not_namespaces

    actors = hosts * per_host
    result: dict[str, Any] = {"actors": actors, "hosts": hosts, "envs_per_actor": 1, "paced": True,
                              "train_args": list(train_args)}
    if why := why_not_namespaces():
        return result | {"refused": [f"cannot make hosts here: {why}"]}
    run_name = f"bench-hosts-{hosts}x{per_host}-{int(time.time())}"
    keys = P.Keys(run_name)
    port = free_port()
    runs_dir = Path(tempfile.mkdtemp(prefix="silcr-bench-hosts-"))
    procs: dict[str, subprocess.Popen] = {}
    logs = []

    def start(name: str, ns: str, *args: str) -> None:
        log = open(runs_dir / f"{name}.log", "w")
        logs.append(log)
        procs[name] = subprocess.Popen(["ip", "netns", "exec", ns, *command(*args)], stdout=log,
                                       stderr=subprocess.STDOUT)  # `ip netns exec` execs: the PID is Python's

    common = ["--run", run_name, "--env", env_id]
    with Namespaces(hosts) as nets:
        try:
            start("router", nets.hub, "router", "--listen", f"tcp/0.0.0.0:{port}")
            hub = ["--connect", f"tcp/127.0.0.1:{port}", "--runs-dir", str(runs_dir), "--learning-starts", "2000",
                   "--stats-interval", "1"]
            start("buffer", nets.hub, "buffer", *common, *hub)
            start("learner", nets.hub, "learner", *common, *hub, "--hidden", *map(str, hidden), "--total-steps",
                  str(10**9), "--eval-episodes", "0", "--weights-interval", str(weights_interval), *train_args)
            for h, ns in enumerate(nets.hosts, start=1):
                start(f"router-{h}", ns, "router", "--listen", "tcp/127.0.0.1:7447",
                      "--connect", f"tcp/{nets.addr(h, 1)}:{port}")
                for k in range((h - 1) * per_host, h * per_host):
                    start(f"actor-{k}", ns, "actor", *common, "--hidden", *map(str, hidden), "--actor-id", str(k),
                          "--zenoh-mode", "client", "--connect", "tcp/127.0.0.1:7447", "--stats-interval", "1")

            def exited() -> str | None:
                for name, p in procs.items():
                    if p.poll() is not None:
                        lines = (runs_dir / f"{name}.log").read_text().strip().splitlines()
                        return f"{name} exited ({p.returncode}): {lines[-1] if lines else ''}"
                return None

            # From the root namespace, over link 0, as a client: a peer here could not reach the
            # hub's peers, which listen on the hub's loopback.
            watcher = session_config([f"tcp/{nets.addr(0, 1)}:{port}"], [], "client")
            with open_session(watcher) as s:
                measured = _window(s, keys, actors, lambda: {n: p.pid for n, p in procs.items()}, seconds,
                                   first_update_s, paced=True, exited=exited)
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            deadline = time.monotonic() + 120
            for p in procs.values():
                try:
                    p.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(10)
            for log in logs:
                log.close()
    shutil.rmtree(runs_dir, ignore_errors=True)
    return result | measured


def _window(session: Any, keys: P.Keys, actors: int, pids: Callable[[], dict[str, int]], seconds: float,
            first_update_s: float, paced: bool, exited: Callable[[], str | None] = lambda: None) -> dict[str, Any]:
    """Wait for the run's steady state, then measure `seconds` of it (or say why there was none).
    `exited` names a component that stopped early, which ends the wait."""
    stats = StatsSnapshot(keys)
    session.declare_subscriber(keys.stats_all, stats.on_sample)
    try:
        wait_until(lambda: exited() or stats.get(keys.stats_learner).get("updates", 0) > 0, first_update_s,
                   "the first update")
        if why := exited():
            return {"refused": [why]}
    except TimeoutError:
        # Measured at 128 actors on 2 cores without throttling: after 8 minutes the
        # actors had collected 30,000 steps and the learner had not yet logged its start.
        buffer = stats.get(keys.stats_buffer)
        return {"starved": f"no update within {first_update_s:.0f} s",
                "episodes_received": buffer.get("episodes_received"),
                "transitions_received": buffer.get("transitions_received")}
    if paced:
        # The rate limiter lets the actors run ahead before the learner's first update (the
        # warm-up plus --spi-tolerance), then pauses them until the learner has caught up.
        # A real run's steady state starts when they go on: the buffer receives new steps.
        held = stats.get(keys.stats_buffer).get("transitions_received", 0)
        try:
            wait_until(lambda: stats.get(keys.stats_buffer).get("transitions_received", 0) > held,
                       first_update_s * 4, "the actors to go on after the learner caught up")
        except TimeoutError:
            return {"starved": f"no new steps within {first_update_s * 4:.0f} s of the first update"}
    first = _snapshot(stats, keys), _cpu_of(pids()), time.monotonic()
    time.sleep(seconds)
    now = pids()  # a restart would change them
    last = _snapshot(stats, keys), _cpu_of(now), time.monotonic()
    rss = [r for name, pid in now.items() if name.startswith("actor-") and (r := rss_mb(pid)) is not None]
    return _report(first, last, actors, rss)


def _snapshot(stats: StatsSnapshot, keys: P.Keys) -> dict[str, Any]:
    snap = stats.as_dict()
    return {"learner": dict(snap["learner"] or {}), "buffer": dict(snap["buffer"] or {}),
            "actors": {k: dict(v) for k, v in snap["actors"].items()}}


def _report(first: tuple, last: tuple, actors: int, rss: list[float]) -> dict[str, Any]:
    (s0, cpu0, t0), (s1, cpu1, t1) = first, last
    dt = t1 - t0
    b0, b1, l0, l1 = s0["buffer"], s1["buffer"], s0["learner"], s1["learner"]

    def cores(name: str) -> float | None:
        a, b = cpu0.get(name), cpu1.get(name)
        return None if a is None or b is None else (b - a) / dt

    def delta(d0: dict, d1: dict, key: str) -> float:
        return float(d1.get(key) or 0) - float(d0.get(key) or 0)

    actor_stats = list(s1["actors"].values())
    p50s = [a["weights_latency_ms_p50"] for a in actor_stats if a.get("weights_latency_ms_p50") is not None]
    p99s = [a["weights_latency_ms_p99"] for a in actor_stats if a.get("weights_latency_ms_p99") is not None]
    actor_cpu = [c for name in cpu1 if name.startswith("actor-") and (c := cores(name)) is not None]
    publications = delta(l0, l1, "weights_published")
    return {
        "window_s": round(dt, 1),
        "actors_reporting": len(actor_stats),
        "episodes_published": int(sum(a.get("episodes_written", 0) for a in actor_stats)),
        "episodes_received": int(b1.get("episodes_received", 0)),
        "episodes_rejected": int(b1.get("episodes_rejected", 0)),
        "episodes_missing": int(b1.get("episodes_missing", 0)),
        "episodes_dropped": int(b1.get("episodes_dropped", 0)),
        "episodes_per_s": delta(b0, b1, "episodes_received") / dt,
        "transitions_per_s": delta(b0, b1, "transitions_received") / dt,
        "weights_latency_ms_p50": float(np.median(p50s)) if p50s else None,
        "weights_latency_ms_p99": max(p99s) if p99s else None,
        "weights_latency_ms_worst_actor_p50": max(p50s) if p50s else None,
        "weights_publications_per_s": publications / dt,
        "weights_bytes": l1.get("weights_bytes"),
        "weights_fanout_mb_per_s": publications * float(l1.get("weights_bytes") or 0) * actors / dt / 1e6,
        "episodes_mb_per_s": delta(b0, b1, "episode_bytes_received") / dt / 1e6,
        "router_cpu_cores": cores("router"),
        "host_routers_cpu_cores": sum(c for name in cpu1 if name.startswith("router-") and (c := cores(name)) is not None)
        if any(name.startswith("router-") for name in cpu1) else None,
        "buffer_cpu_cores": cores("buffer"),
        "learner_cpu_cores": cores("learner"),
        "actors_cpu_cores": sum(actor_cpu) if actor_cpu else None,
        "actor_rss_mb_median": float(np.median(rss)) if rss else None,
        "actor_rss_mb_max": max(rss) if rss else None,
        "learner_duty_cycle": l1.get("duty_cycle"),
        "learner_updates_per_s": delta(l0, l1, "updates") / dt,
    }


def run(out_dir: Path, quick: bool = False, counts: list[int] | None = None, envs_per_actor: int = 1,
        env_id: str = "Hopper-v5", seconds: float | None = None, paced: bool = False,
        train_args: list[str] = (), tag: str = "", hosts: int = 0) -> list[dict[str, Any]]:
    """Measure each count in turn; `tag` names the records (scale-<tag>.json, scale-<tag>.png).

    With `hosts`, each count is the actors per host, on that many network-namespace hosts."""
    name = f"scale-{tag}" if tag else "scale"
    paced = paced or hosts > 0
    counts = counts or ([2, 4] if quick else [8, 32, 128])
    seconds = seconds or (10.0 if quick else 60.0)
    hidden = [64, 64] if quick else [800, 400]  # the paper's networks: 1.3 MB of Hopper weights per publication
    results = []
    for n in counts:
        where = f"{hosts} hosts x {n} actors" if hosts else f"{n} actors x {envs_per_actor} env(s)"
        print(f"silcr bench scale: {where}, {seconds:.0f} s window, "
              f"{'paced by the learner' if paced else 'actors unthrottled'} {' '.join(train_args)}...", flush=True)
        if hosts:
            results.append(measure_hosts(hosts, n, seconds, env_id, hidden, weights_interval=50,
                                         train_args=train_args))
        else:
            results.append(measure(n, seconds, env_id, envs_per_actor, hidden, weights_interval=50, paced=paced,
                                   train_args=train_args))
        # after every count, so that a later count that runs long or is stopped loses nothing
        write_json(out_dir, name, {"env": env_id, "hidden": hidden, "window_s": seconds, "paced": paced, "hosts": hosts,
                                   "train_args": list(train_args), "results": results})
    keys = list(dict.fromkeys(k for r in results for k in r
                              if k not in ("actors", "hosts", "envs_per_actor", "paced", "train_args")))
    print_table(f"scale: silcr train on {env_id}, networks {hidden}, window {seconds:.0f} s",
                ["metric", *[f"{r['actors']} actors" for r in results]],
                [[k, *[_fmt(r.get(k)) for r in results]] for k in keys])
    _figure(out_dir, results, name)
    return results


def _fmt(v: Any) -> Any:
    return round(v, 3) if isinstance(v, float) else v


def _figure(out_dir: Path, results: list[dict[str, Any]], name: str = "scale") -> None:
    """One panel per quantity against the actor count (docs/performance.md shows it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [r for r in results if "window_s" in r]
    if not shown:
        return
    panels = ["episodes_per_s", "weights_latency_ms_p50", "weights_latency_ms_p99", "weights_fanout_mb_per_s",
              "episodes_mb_per_s", "router_cpu_cores", "buffer_cpu_cores", "actor_rss_mb_median",
              "learner_duty_cycle"]
    fig, axes = plt.subplots(3, 3, figsize=(12, 9))
    for ax, key in zip(axes.flat, panels):
        xs = [r["actors"] for r in shown if r.get(key) is not None]
        ys = [r[key] for r in shown if r.get(key) is not None]
        ax.plot(xs, ys, "o-")
        ax.set_xscale("log", base=2)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("actors")
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_dir / f"{name}.png", dpi=100)
    plt.close(fig)
