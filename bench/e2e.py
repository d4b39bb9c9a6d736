"""End-to-end benchmark: a real `silcr train` run, measured from its own stats topics, and the same
budget with `--single-process` (one process, no Zenoh), measured from its progress.csv."""

from __future__ import annotations

import csv
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from silcr.common import protocol as P
from silcr.common import run_layout
from silcr.common.commands import command

from silcr.deploy.monitor import StatsSnapshot

from .procs import Components, free_port, wait_until
from .timing import print_table, write_json


def run(out_dir: Path, quick: bool = False, env_id: str = "Hopper-v5", actors: int = 2) -> dict[str, Any]:
    updates = 300 if quick else 2000
    warmup = 2000
    run_name = f"bench-e2e-{int(time.time())}"
    keys = P.Keys(run_name)
    port = free_port()
    runs_dir = tempfile.mkdtemp(prefix="silcr-bench-e2e-")
    proc = subprocess.Popen(
        command("train", "--run", run_name, "--runs-dir", runs_dir, "--env", env_id, "--actors", str(actors),
                "--learning-starts", str(warmup), "--total-steps", str(warmup + updates), "--eval-episodes", "0",
                "--stats-interval", "0.5", "--zenoh-listen", f"tcp/127.0.0.1:{port}"),
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
    )
    comp = Components()
    comp.endpoint = f"tcp/127.0.0.1:{port}"
    last: dict[str, Any] = {}
    actor_stats: dict[str, Any] = {}
    try:
        with comp.session() as s:
            stats = StatsSnapshot(keys)
            s.declare_subscriber(keys.stats_all, stats.on_sample)
            wait_until(lambda: stats.get(keys.stats_learner).get("updates", 0) > 0, 300, "the first update")
            while proc.poll() is None:
                cur = stats.get(keys.stats_learner)
                if "duty_cycle" in cur:  # the final message is a short summary
                    last = cur
                for i in range(actors):
                    a = stats.get(keys.stats_actor(i))
                    if a.get("weights_latency_ms_p50") is not None:
                        actor_stats[str(i)] = a
                time.sleep(0.2)
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.wait(60)
    latencies = [a["weights_latency_ms_p50"] for a in actor_stats.values()]
    result = {
        "env": env_id, "actors": actors, "updates": last.get("updates"), "updates_per_s": last.get("updates_per_s"),
        "learner_duty_cycle": last.get("duty_cycle"), "batch_wait_ms_p50": last.get("batch_wait_ms_p50"),
        "batch_wait_ms_p99": last.get("batch_wait_ms_p99"), "policy_lag_mean": last.get("policy_lag_mean"),
        "weights_latency_ms_p50": sum(latencies) / len(latencies) if latencies else None,
        "single_process_updates_per_s": _single_process_rate(env_id, actors, warmup, updates),
    }
    print_table(f"end to end: silcr train on {env_id}, {actors} actors, 800-400",
                ["metric", "value"], [[k, v] for k, v in result.items()])
    write_json(out_dir, "e2e", {"results": result})
    return result


def _single_process_rate(env_id: str, actors: int, warmup: int, updates: int) -> float:
    """Updates per second of the same budget in one process (both cores for torch), warm-up included as above."""
    runs_dir = Path(tempfile.mkdtemp(prefix="silcr-bench-single-"))
    subprocess.run(
        command("train", "--single-process", "--run", "single", "--runs-dir", str(runs_dir), "--env", env_id,
                "--actors", str(actors), "--learning-starts", str(warmup), "--total-steps", str(warmup + updates),
                "--eval-episodes", "1", "--eval-interval", str(10 * (warmup + updates))),
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, check=True, timeout=3600,
    )
    last = list(csv.DictReader(open(run_layout.progress(runs_dir / "single"))))[-1]
    return float(last["updates_per_s"])
