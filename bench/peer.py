"""`silcr bench peer`: silcr against the library a user would otherwise pick, Stable-Baselines3's SAC,
on the same work, measured in the same run.

Three programs train SAC with the dense reward on Hopper-v5 with the same networks, batch,
learning rate, tau, gamma, warm-up and budget, evaluation off, each with its own defaults
otherwise (threads included, as a user would run them):

- `sb3`: Stable-Baselines3's `SAC("MlpPolicy", ...)` (the optional extra `pip install -e ".[bench]"`);
- `distributed`: `silcr train` with its defaults (a buffer service, a learner and one actor over Zenoh);
- `single-process`: `silcr train --single-process`.

They run alternated, round after round, so that each round exposes all three to the same
background load, and the bench reports each silcr program's wall and CPU time (user + sys of the
whole process tree) as ratios to SB3's of the same round: min, median and max over the rounds.
Each program reports the updates it made, so the table also shows that the work was the same.

For silcr's programs the bench also reads the learner's log: the torch threads it chose and how
long its updates took from the first to the last. Each round then times the same update alone
at those threads, in a fresh process whose OpenMP threads wait as the program's do (the update's
floor on this machine, in the same run), and the
table gives each program's learner rate as a share of that floor: 1 means the learner trained as
fast as the update alone can run, and a lower share is time lost to waits, to the processes
beside it and to the data path.
"""

from __future__ import annotations

import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from silcr.common import run_layout
from silcr.common.algorithms import ALGORITHMS
from silcr.common.commands import command

from .procs import free_port
from .timing import print_table, write_json

PROGRAMS = ("sb3", "distributed", "single-process")
#: SB3's SAC is plain SAC: the registry's algorithm that learns from the env's reward and keeps no D_E.
PLAIN_SAC = next(a.name for a in ALGORITHMS.values() if a.uses_env_reward and not a.keeps_expert)
MISSING_SB3 = ("silcr bench peer: Stable-Baselines3 is not installed; install the bench extra "
               "(pip install -e \".[bench]\", or pip install stable-baselines3) and run it again")


@dataclass(frozen=True)
class PeerConfig:
    """What both libraries are told; everything else is each one's default."""

    hidden: tuple[int, ...] = (256, 256)
    env_id: str = "Hopper-v5"
    batch_size: int = 128
    lr: float = 3e-4
    tau: float = 0.005
    gamma: float = 0.99
    learning_starts: int = 5000
    total_steps: int = 15000
    seed: int = 0

    def silcr_args(self, runs_dir: Path, run: str, single_process: bool) -> list[str]:
        """`silcr train` options: one update per env step after the warm-up (silcr's default), no evaluation."""
        return ["train", "--run", run, "--runs-dir", str(runs_dir), "--env", self.env_id, "--algo", PLAIN_SAC,
                "--reward", "dense", "--hidden", *map(str, self.hidden), "--batch-size", str(self.batch_size),
                "--lr", str(self.lr), "--tau", str(self.tau), "--gamma", str(self.gamma),
                "--learning-starts", str(self.learning_starts), "--total-steps", str(self.total_steps),
                "--seed", str(self.seed), "--eval-episodes", "0",
                *(["--single-process"] if single_process else ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"])]

    def sb3_kwargs(self) -> dict[str, Any]:
        """`stable_baselines3.SAC` arguments: one gradient step per env step after the warm-up (SB3's default)."""
        return {"policy": "MlpPolicy", "learning_rate": self.lr, "buffer_size": self.total_steps,
                "learning_starts": self.learning_starts, "batch_size": self.batch_size, "tau": self.tau,
                "gamma": self.gamma, "train_freq": 1, "gradient_steps": 1, "seed": self.seed, "device": "cpu",
                "policy_kwargs": {"net_arch": list(self.hidden)}, "verbose": 0}


# Run in a plain interpreter, in the environment as it was before silcr set its thread-pool defaults
# (silcr/__init__.py): the peer runs with its own, as a user would run it.
SB3_SCRIPT = """
import json, sys
import gymnasium as gym
from stable_baselines3 import SAC
cfg = json.loads(sys.argv[1])
model = SAC(env=gym.make(cfg["env_id"]), **cfg["kwargs"])
model.learn(total_timesteps=cfg["total_steps"])
print(json.dumps({"updates": int(model._n_updates), "env_steps": int(model.num_timesteps)}))
"""


def sb3_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("stable_baselines3") is not None


def _peer_env() -> dict[str, str]:
    """This process's environment without the thread-pool defaults silcr added (a value the user set stays)."""
    from silcr.common.process_env import ENV_BEFORE_DEFAULTS

    env = dict(os.environ)
    for name, value in ENV_BEFORE_DEFAULTS.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value
    return env


def _timed(cmd: list[str], timeout: float, env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """Wall and CPU seconds (user + sys of the process and every child it waited for) of one command, and its stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-5:]
        raise RuntimeError(f"{' '.join(cmd[:1] + cmd[3:6])}... exited {r.returncode}: " + " | ".join(tail))
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, r.stdout


def run_once(program: str, cfg: PeerConfig, timeout: float = 3600) -> dict[str, Any]:
    """One training run of `program`: its wall and CPU seconds and the work it did."""
    if program == "sb3":
        payload = json.dumps({"env_id": cfg.env_id, "total_steps": cfg.total_steps, "kwargs": cfg.sb3_kwargs()})
        wall, cpu, out = _timed([sys.executable, "-c", SB3_SCRIPT, payload], timeout, env=_peer_env())
        work = json.loads(out.strip().splitlines()[-1])
    else:
        import torch

        runs_dir = Path(tempfile.mkdtemp(prefix=f"silcr-bench-peer-{program}-"))
        # Without the thread-pool defaults this process took from silcr: a user's shell has none.
        wall, cpu, _ = _timed(command(*cfg.silcr_args(runs_dir, "peer", program == "single-process")), timeout,
                              env=_peer_env())
        counters = torch.load(run_layout.learner_checkpoint(runs_dir / "peer"), map_location="cpu",
                              weights_only=True)["counters"]
        log = run_layout.single_process_log(runs_dir / "peer") if program == "single-process" \
            else run_layout.component_log(runs_dir / "peer", "learner")
        account = learner_account(log.read_text(errors="replace"))
        shutil.rmtree(runs_dir, ignore_errors=True)  # its checkpoints: tens of MB a run
        work = {"updates": int(counters["updates"]), "env_steps": int(counters["env_steps"])} | account
    return {"program": program, "wall_s": wall, "cpu_s": cpu, **work}


# The learner's own account of its training (learner/bookkeeping.py, `Bookkeeping.finish`, and the thread probe).
LEARNER_SPAN = re.compile(r"training: (\d+) updates in ([\d.]+) s from the first to the last .*?([\d.]+) s of it in updates")
LEARNER_THREADS = re.compile(r"torch threads: (\d+)")


def learner_account(log_text: str) -> dict[str, Any]:
    """Threads, updates and seconds from a learner's log: what the floor is compared with."""
    span = LEARNER_SPAN.search(log_text)
    threads = LEARNER_THREADS.search(log_text)
    if span is None:
        return {}
    return {"threads": int(threads.group(1)) if threads else None, "span_updates": int(span.group(1)),
            "span_s": float(span.group(2)), "in_updates_s": float(span.group(3))}


def floor_ms(cfg: PeerConfig, threads: int, updates: int = 200) -> float:
    """Milliseconds per update of the same SAC update alone in this process (median of 5 runs of updates/5)."""
    import torch

    from silcr.common.envs import EnvSpec
    from silcr.learner import denormals
    from silcr.learner.sac import Sac, SacHyper
    from silcr.learner.threads import time_per_update
    from silcr.learner.update import synthetic_batch

    spec = EnvSpec.of(cfg.env_id)
    before = torch.get_num_threads()
    try:
        sac = Sac(spec.obs_dim, spec.act_dim, list(cfg.hidden), SacHyper(cfg.gamma, cfg.tau, cfg.lr), torch.device("cpu"))
        batch = synthetic_batch(spec, cfg.batch_size)
        with denormals.flushed(torch.device("cpu")):
            time_per_update(lambda: sac.update(*batch), threads, 20)  # warm-up
            times = [time_per_update(lambda: sac.update(*batch), threads, updates // 5) for _ in range(5)]
        return 1000 * statistics.median(times)
    finally:
        torch.set_num_threads(before)


FLOOR_SCRIPT = """
import json, sys
import silcr
if sys.argv[2] == "single-process":
    silcr.spin_in_single_process()  # its threads wait as that program's do
from silcr.bench.peer import PeerConfig, floor_ms
cfg = json.loads(sys.argv[1])
print(floor_ms(PeerConfig(**cfg | {"hidden": tuple(cfg["hidden"])}), int(sys.argv[3])))
"""


def program_floor_ms(cfg: PeerConfig, program: str, threads: int) -> float:
    """`floor_ms` in a fresh process whose OpenMP threads wait as `program`'s learner's do (a pool's policy is fixed at load)."""
    out = subprocess.run([sys.executable, "-c", FLOOR_SCRIPT, json.dumps(asdict(cfg)), program, str(threads)],
                         env=_peer_env(), capture_output=True, text=True, timeout=600, check=True).stdout
    return float(out.strip().splitlines()[-1])


def _spread(values: list[float]) -> dict[str, float]:
    return {"min": min(values), "median": statistics.median(values), "max": max(values)}


def compare(cfg: PeerConfig, rounds: int) -> dict[str, Any]:
    """`rounds` rounds of the three programs in turn (the order rotates), and silcr's ratios to SB3 per round."""
    per_round: list[dict[str, dict[str, Any]]] = []  # each round's runs by program
    for r in range(rounds):
        got = {}
        for program in PROGRAMS[r % 3:] + PROGRAMS[:r % 3]:
            got[program] = run_once(program, cfg) | {"round": r}
            print(f"  {'x'.join(map(str, cfg.hidden))} round {r + 1}/{rounds} {program}: "
                  f"{got[program]['wall_s']:.1f} s wall, {got[program]['cpu_s']:.1f} s CPU, "
                  f"{got[program]['updates']} updates", flush=True)
        # The floor, alone, after the round's runs, at the threads the distributed learner chose.
        for program in PROGRAMS[1:]:
            run = got[program]
            if run.get("span_s"):
                run["floor_ms"] = program_floor_ms(cfg, program, run.get("threads") or 1)
                run["rate_vs_floor"] = run["floor_ms"] * run["span_updates"] / (1000 * run["span_s"])
                run["duty_cycle"] = run["in_updates_s"] / run["span_s"]
        print("  update floor, alone, at the learner's threads: " + ", ".join(
            f"{p} {got[p].get('floor_ms', float('nan')):.2f} ms ({got[p].get('threads')} thread(s); learner rate / floor "
            f"{got[p].get('rate_vs_floor', float('nan')):.2f})" for p in PROGRAMS[1:]), flush=True)
        per_round.append(got)
    ratios = {f"{program}_{what.removesuffix('_s')}": _spread([got[program][what] / got["sb3"][what] for got in per_round])
              for program in PROGRAMS[1:] for what in ("wall_s", "cpu_s")}
    for program in PROGRAMS[1:]:
        for what in ("rate_vs_floor", "duty_cycle"):
            values = [got[program][what] for got in per_round if what in got[program]]
            if values:
                ratios[f"{program}_{what}"] = _spread(values)
    return {"config": asdict(cfg), "runs": [got[p] for got in per_round for p in PROGRAMS], "ratios": ratios}


def run(out_dir: Path, quick: bool = False, rounds: int = 0) -> dict[str, Any]:
    if not sb3_available():
        raise SystemExit(MISSING_SB3)
    if quick:  # a smoke test of the bench: small budget, one round, the small network
        configs = [PeerConfig(hidden=(256, 256), learning_starts=500, total_steps=800)]
    else:
        configs = [PeerConfig(hidden=(256, 256)), PeerConfig(hidden=(800, 400))]
    rounds = rounds or (1 if quick else 3)
    results = []
    for cfg in configs:
        print(f"silcr bench peer: {cfg.env_id}, SAC dense, {'x'.join(map(str, cfg.hidden))}, batch {cfg.batch_size}, "
              f"{cfg.learning_starts:,} warm-up + {cfg.total_steps - cfg.learning_starts:,} steps, {rounds} round(s)",
              flush=True)
        results.append(compare(cfg, rounds))
    rows = []
    for res in results:
        net = "x".join(map(str, res["config"]["hidden"]))
        for program, label in (("distributed", "silcr train (defaults)"), ("single-process", "silcr train --single-process")):
            for what in ("wall", "cpu"):
                s = res["ratios"][f"{program}_{what}"]
                rows.append([net, label, f"{what} / SB3's", s["min"], s["median"], s["max"]])
            for what, name in (("rate_vs_floor", "learner rate / update floor"), ("duty_cycle", "learner duty cycle")):
                if f"{program}_{what}" in res["ratios"]:
                    s = res["ratios"][f"{program}_{what}"]
                    rows.append([net, label, name, s["min"], s["median"], s["max"]])
        for program in PROGRAMS:
            mine = [x for x in res["runs"] if x["program"] == program]
            rows.append([net, program, "updates, median wall s", statistics.median(x["updates"] for x in mine),
                         statistics.median(x["wall_s"] for x in mine), ""])
    print_table("silcr against Stable-Baselines3's SAC, same work, alternated (ratio < 1: silcr is faster)",
                ["network", "program", "quantity", "min", "median", "max"], rows)
    write_json(out_dir, "peer", {"results": results})
    return {"results": results}
