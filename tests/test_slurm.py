"""silcr on a real Slurm cluster (issue 64): deploy/slurm/silcr.sbatch over three nodes in network namespaces, each
with its own address (tests/slurm_cluster.py): the router, the buffer and the learner on the first node, two actors
on each of the other two, every client connecting to the first node's address.

Checked: the run finishes and the job completes with exit code 0; actors ran on both compute nodes (their stats,
read through the router from this host, name both, and each node wrote its actors' logs); the buffer received
every episode the actors wrote, none missing or rejected; a requeue of the finished run's job exits 0 at once and
changes nothing; `scancel` of a second job mid-run leaves no silcr process anywhere and checkpoints that load.
What it cannot show: a real network between machines, a shared filesystem other than this machine's disk.

Skipped, with the reason, when not root or when Debian's slurmctld, slurmd and munge cannot be installed.
"""

from __future__ import annotations

import hashlib
import os
import re
import subprocess
from pathlib import Path

import pytest

from silcr.common import protocol as P
from tests import slurm_cluster
from tests.helpers import REPO, SMALL_FINITE_RUN_TOML, LatestJson, client_when_up, wait_for

pytestmark = pytest.mark.slow

SBATCH = REPO / "deploy" / "slurm" / "silcr.sbatch"
SMALL_TOML = 'env = "InvertedPendulum-v5"\n' + SMALL_FINITE_RUN_TOML


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    why = slurm_cluster.problem()
    if why is not None:
        pytest.skip(why)
    c = slurm_cluster.Cluster(tmp_path_factory.mktemp("slurm")).start()
    yield c
    c.close()


def _submit(cluster, shared: Path, run: str, total_steps: int, port: int) -> str:
    config = shared / f"{run}.toml"
    config.write_text(SMALL_TOML + f"total_steps = {total_steps}\n")
    env = {**cluster.env, "SILCR_RUN": run, "PATH": os.environ["PATH"]}
    r = subprocess.run(["sbatch", "--parsable", "--nodes=3", f"--output={shared}/{run}-%j.out", f"--chdir={shared}",
                        str(SBATCH), "--dir", str(shared), "--config", str(config), "--actors-per-node", "2",
                        "--port", str(port)], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip().split(";")[0]


def _ended(cluster, job: str) -> dict[str, str] | None:
    fields = cluster.job(job)
    return fields if fields.get("JobState") in ("COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL") else None


def _silcr_processes() -> list[str]:
    out = subprocess.run(["pgrep", "-af", "silcr (router|buffer|learner|actor)"], capture_output=True, text=True)
    return [line for line in out.stdout.splitlines() if "pgrep" not in line]


def _files(run_dir: Path) -> dict[str, str]:
    return {str(p.relative_to(run_dir)): hashlib.sha256(p.read_bytes()).hexdigest() for p in run_dir.rglob("*")
            if p.is_file() and p.relative_to(run_dir).parts[0] not in ("logs", ".lock")}


def test_a_run_over_three_nodes_finishes_with_actors_on_both_compute_nodes(cluster, tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    port = 27000 + int(cluster.tag, 16) % 1000
    job = _submit(cluster, shared, "onslurm", 6000, port)
    # The stats, through the router on the first node, from this host (the controller's address).
    session = client_when_up(port, timeout=180, host=cluster.node_addr(1))
    try:
        keys = P.Keys("onslurm")
        stats = LatestJson(session, keys.stats_all)
        fields = wait_for(lambda: _ended(cluster, job), 600, f"job {job} to end", interval=1)
        actors = {k: v for k, v in stats.latest.items() if k.startswith(keys.prefix + "/stats/actor/")}
    finally:
        session.close()
    out = (shared / f"onslurm-{job}.out").read_text()
    assert fields["JobState"] == "COMPLETED" and fields["ExitCode"] == "0:0", (fields, out[-3000:])
    run_dir = shared / "runs" / "onslurm"
    assert (run_dir / "finished.json").exists() and "run onslurm finished" in out
    # two actors on each compute node, by their stats (keys and hosts) and by their logs
    assert len(actors) == 4, sorted(actors)
    assert {a["host"] for a in actors.values()} == set(cluster.names[1:]), actors
    logs = run_dir / "logs"
    assert {p.name.split("-")[1] for p in logs.glob("actor-*.log")} == set(cluster.names[1:])
    # every episode an actor wrote reached the buffer: none missing, none rejected, the counts equal
    written = 0
    for log in logs.glob("actor-*.log"):
        m = re.search(r"stopping \(.*\): \d+ episodes, \d+ steps; (\d+) episodes written to the buffer", log.read_text())
        assert m, log.read_text()[-2000:]
        written += int(m.group(1))
    buffer = (logs / "buffer.log").read_text()
    m = re.search(r"buffer stopping \(.*\): (\d+) episodes, \d+ transitions received, (\d+) rejected, (\d+) missing",
                  buffer)
    assert m, buffer[-2000:]
    assert (int(m.group(1)), int(m.group(2)), int(m.group(3))) == (written, 0, 0) and written > 0

    # The finished run stays finished: requeued, its job exits 0 at once and changes no file of the run.
    before = _files(run_dir)
    assert cluster.run("scontrol", "requeue", job).returncode == 0
    wait_for(lambda: cluster.job(job).get("JobState") == "COMPLETED" and
             int(cluster.job(job).get("Restarts", "0")) >= 1, 300, "the requeued job to end", interval=1)
    assert cluster.job(job)["ExitCode"] == "0:0"
    assert "run onslurm already finished at " in (logs / "learner.log").read_text()
    assert _files(run_dir) == before
    assert _silcr_processes() == []


def test_scancel_mid_run_stops_every_process_and_leaves_usable_checkpoints(cluster, tmp_path):
    from silcr.buffer_service.replay import open_replay
    from silcr.common.config import from_options
    from silcr.common.envs import EnvSpec
    from silcr.learner.checkpoint import load_checkpoint

    shared = tmp_path / "shared"
    shared.mkdir()
    port = 28000 + int(cluster.tag, 16) % 1000
    job = _submit(cluster, shared, "cancelled", 10_000_000, port)
    run_dir = shared / "runs" / "cancelled"
    wait_for(lambda: (run_dir / "checkpoints" / "learner.pt").exists() and
             (run_dir / "checkpoints" / "buffer.ckpt").exists(), 300, "both checkpoints")
    assert cluster.run("scancel", job).returncode == 0
    fields = wait_for(lambda: _ended(cluster, job), 120, f"job {job} to end", interval=1)
    assert fields["JobState"] == "CANCELLED"
    wait_for(lambda: _silcr_processes() == [], 60, "every silcr process to exit")
    counters = load_checkpoint(run_dir / "checkpoints" / "learner.pt")["counters"]
    assert counters["updates"] > 0
    cfg = from_options({"run": "cancelled", "runs_dir": str(shared / "runs"), "env": "InvertedPendulum-v5",
                        "expert_capacity": 1000, "learning_starts": 500, "resume": True}, "buffer")
    _, snap = open_replay(cfg, EnvSpec.of(cfg.env))  # what a --resume would restore
    assert snap is not None and snap.transitions > 0
    assert not (run_dir / "finished.json").exists()
    assert "stopping (SIGTERM)" in (run_dir / "logs" / "learner.log").read_text()


def test_the_signal_before_the_time_limit_checkpoints_requeues_and_the_run_goes_on_to_finish(cluster, tmp_path):
    """`--signal=B:USR1@120`, sent here by hand (`scancel --signal=USR1 --batch`), as Slurm sends it two minutes
    before the time limit: the job stops every component with its checkpoints and requeues itself; the requeued
    job resumes from them and finishes the run."""
    shared = tmp_path / "shared"
    shared.mkdir()
    port = 29000 + int(cluster.tag, 16) % 1000
    job = _submit(cluster, shared, "requeued", 6000, port)
    run_dir = shared / "runs" / "requeued"
    wait_for(lambda: (run_dir / "checkpoints" / "learner.pt").exists() and (run_dir / "progress.csv").exists() and
             len((run_dir / "progress.csv").read_text().splitlines()) >= 3, 300, "a learner checkpoint")
    assert cluster.run("scancel", "--signal=USR1", "--batch", job).returncode == 0
    fields = wait_for(lambda: (f := cluster.job(job)).get("JobState") == "COMPLETED" and int(f.get("Restarts", "0")) >= 1
                      and f, 600, "the requeued job to finish the run", interval=1)
    assert fields["ExitCode"] == "0:0"
    out = (shared / f"requeued-{job}.out").read_text()
    assert "the time limit is near: checkpointing, then requeueing the job" in out and "run requeued finished" in out
    assert "resumed from " in (run_dir / "logs" / "learner.log").read_text()
    steps = [int(line.split(",")[1]) for line in (run_dir / "progress.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and steps[-1] >= 6000
    assert _silcr_processes() == []
