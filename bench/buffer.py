"""Buffer benchmark: inserts and mixed batches per second, in-process and over Zenoh; memory per transition.

The reference is the learner's batch demand measured in the same run (updates/s
of `learner.sac.Sac` at the paper's networks on this machine), so the headline
figure is "how many learners this buffer can feed".
"""

from __future__ import annotations

import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zenoh

from silcr.buffer_service.batches import compose_batches
from silcr.buffer_service.episode_log import EpisodeLog
from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.lifecycle import StopFlag
from silcr.common.sample_channel import ZenohBatchStream
from silcr.deploy.monitor import StatsSnapshot
from silcr.learner.sac import Sac, SacHyper

from .procs import Components, wait_until
from .reference_sac import random_batch
from .timing import print_table, rate, write_json

TASKS = {"Hopper": "Hopper-v5", "Humanoid": "Humanoid-v5"}


def _episodes(spec: EnvSpec, n: int, length: int, seed: int = 0) -> list[bytes]:
    g = np.random.default_rng(seed)
    out = []
    for i in range(n):
        rewards = np.zeros(length, np.float32)
        rewards[-1] = g.normal()
        ep = P.Episode(0, i, 0, float(rewards.sum(dtype=np.float64)), False, True,
                       g.normal(size=(length + 1, spec.obs_dim)).astype(np.float32),
                       g.uniform(-1, 1, (length, spec.act_dim)).astype(np.float32), rewards)
        out.append(ep.encode())
    return out


def learner_demand(obs_dim: int, act_dim: int, n: int = 10) -> float:
    sac = Sac(obs_dim, act_dim, [800, 400], SacHyper(), torch.device("cpu"))
    b = random_batch(obs_dim, act_dim, 128, torch.device("cpu"))
    sac.update(*b)
    return rate(lambda: sac.update(*b), n)


def memory_per_transition(spec: EnvSpec, length: int, transitions: int) -> tuple[float, float]:
    """Measured bytes per stored transition (tracemalloc) and the minimum (obs + action + reward + flag)."""
    cfg = Config(run="bench", env=spec.env_id, online_capacity=transitions, expert_capacity=max(1, transitions // 20))
    payloads = _episodes(spec, transitions // length, length)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    state = ReplayState(cfg, spec)
    for p in payloads:
        state.intake.ingest(p)
    del payloads
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    used = sum(s.size_diff for s in after.compare_to(before, "filename"))
    minimum = (spec.obs_dim + spec.act_dim + 1) * 4 + 1
    # D_E keeps its own copy of its episodes (for vectorised sampling): they count as stored.
    return used / (len(state.fifo) + len(state.heap)), float(minimum)


def preallocated_bytes(spec: EnvSpec, online: int, expert: int) -> int:
    """What the two tables reserve at their first episode (pages are touched only as they fill)."""
    state = ReplayState(Config(run="bench", env=spec.env_id, online_capacity=online, expert_capacity=expert), spec)
    state.intake.ingest(_episodes(spec, 1, 10)[0])
    return state.fifo.storage.nbytes() + state.heap.storage.nbytes()


def run(out_dir: Path, quick: bool = False) -> dict[str, Any]:
    results: dict[str, Any] = {}
    rows, log_rows = [], []
    for name, env_id in TASKS.items():
        spec = EnvSpec.of(env_id)
        demand = learner_demand(spec.obs_dim, spec.act_dim, 3 if quick else 10)
        # in-process
        cfg = Config(run="bench", env=env_id, learning_starts=1000, spi_tolerance=1e9)
        payloads = _episodes(spec, 10 if quick else 50, 1000)
        timings, logged = [], []
        for i in range(5):  # median of repeats: the first can meet torch's OpenMP threads still spinning
            state = ReplayState(cfg, spec)
            t0 = time.perf_counter()
            for p in payloads:
                state.intake.ingest(p)
            timings.append(time.perf_counter() - t0)
            # The same with the episode log (issue 63): each episode appended and handed to the operating
            # system before the next, the most a buffer flushes (it flushes once per burst of arrivals).
            state = ReplayState(cfg, spec)
            log = EpisodeLog(out_dir / f"episode-log-{name}-{i}")
            t0 = time.perf_counter()
            for p in payloads:
                state.intake.ingest(p)
                log.append(p)
                log.flush()
            logged.append(time.perf_counter() - t0)
            log.close(checkpointed=True)
        inserts = 1000 * len(payloads) / float(np.median(timings))
        inserts_logged = 1000 * len(payloads) / float(np.median(logged))
        log_bytes_per_transition = (sum(map(len, payloads)) + 8 * len(payloads)) / (1000 * len(payloads))
        req = P.SampleRequest(1, 128).encode()
        batches = rate(lambda: state.sampler.answer(req).encode(), 50 if quick else 300)
        # The gather alone at 32 batches per request: what a GPU learner's data path could draw.
        gather = 32 * rate(lambda: compose_batches(state.fifo, state.heap, 32, 128, state.rng, state.labeller, spec.obs_dim,
                                                   spec.act_dim), 10 if quick else 50)
        # over Zenoh, buffer in its own process
        zinserts, zbatches = _over_zenoh(env_id, payloads, quick)
        # The log's cost over Zenoh, where it counts: alternating runs with and without it, the median of each
        # (one run of 50 episodes each way differed by +-25% from run to run here).
        logged_runs, unlogged_runs = [zinserts], []
        for _ in range(1 if quick else 3):
            unlogged_runs.append(_over_zenoh(env_id, payloads, quick, "--no-episode-log", sample=False)[0])
            logged_runs.append(_over_zenoh(env_id, payloads, quick, sample=False)[0])
        zinserts_logged, zinserts_unlogged = float(np.median(logged_runs)), float(np.median(unlogged_runs))
        bytes_per, minimum = memory_per_transition(spec, 1000, 20_000 if quick else 100_000)
        paper_gb = preallocated_bytes(spec, 1_000_000, 50_000) / 1e9
        results[name] = {
            "learner_updates_per_s": demand, "inserts_per_s_in_process": inserts, "batches_per_s_in_process": batches,
            "gathered_batches_per_s_32_per_request": gather,
            "inserts_per_s_in_process_with_episode_log": inserts_logged,
            "episode_log_vs_none_in_process": inserts_logged / inserts,
            "inserts_per_s_zenoh": zinserts, "batches_per_s_zenoh": zbatches,
            "inserts_per_s_zenoh_median_logged": zinserts_logged,
            "inserts_per_s_zenoh_median_no_episode_log": zinserts_unlogged,
            "episode_log_vs_none_zenoh": zinserts_logged / zinserts_unlogged,
            "episode_log_bytes_per_transition": log_bytes_per_transition,
            "zenoh_batches_vs_learner_demand": zbatches / demand,
            "bytes_per_transition": bytes_per, "minimum_bytes_per_transition": minimum,
            "memory_overhead": bytes_per / minimum - 1,
            "reserved_gb_for_1e6_online_5e4_expert": paper_gb,
        }
        rows.append([name, inserts, batches, gather, zinserts, zbatches, demand, zbatches / demand, bytes_per, minimum, paper_gb])
        log_rows.append([name, inserts, inserts_logged, inserts_logged / inserts, zinserts_unlogged, zinserts_logged,
                         zinserts_logged / zinserts_unlogged, log_bytes_per_transition])
    print_table("buffer (batch 128, 1000-step episodes)",
                ["task", "inserts/s", "batches/s", "gathered/s (32 per request)", "inserts/s zenoh", "batches/s zenoh",
                 "learner/s", "zenoh x learner", "B/transition", "minimum B", "GB, 1e6 + 5e4"], rows)
    print_table("the episode log's cost (transitions/s; each stored episode logged before it is acknowledged)",
                ["task", "in-process", "in-process, logged", "ratio", "zenoh, --no-episode-log (median)",
                 "zenoh, logged (median)", "ratio", "log B/transition"], log_rows)
    payload = {"results": results}
    write_json(out_dir, "buffer", payload)
    return payload


def _over_zenoh(env_id: str, payloads: list[bytes], quick: bool, *options: str, sample: bool = True) -> tuple[float, float]:
    run = f"bench-buffer-{int(time.time())}"
    keys = P.Keys(run)
    comp = Components()
    try:
        comp.start("router")
        comp.start("buffer", "--run", run, "--env", env_id, "--learning-starts", "1000", "--spi-tolerance", "1e9",
                   "--stats-interval", "0.2", "--runs-dir", str(comp.dir), *options)
        with comp.session() as s:
            stats = StatsSnapshot(keys)
            s.declare_subscriber(keys.stats_all, stats.on_sample)
            pub = s.declare_publisher(keys.episodes, congestion_control=zenoh.CongestionControl.BLOCK)
            wait_until(lambda: pub.matching_status.matching, 60, "the buffer service")
            t0 = time.perf_counter()
            for p in payloads:
                pub.put(p)
            wait_until(lambda: stats.get(keys.stats_buffer).get("episodes_received", 0) >= len(payloads), 120, "episodes")
            inserts = 1000 * len(payloads) / (time.perf_counter() - t0)
            if not sample:
                return inserts, 0.0
            # The learner's own client: 4 batches per query, 4 queries in flight.
            stream = ZenohBatchStream(s, keys, P.SampleRequest(4, 128), 4, StopFlag())
            stream.wait_for_buffer()
            n = 50 if quick else 250
            t0 = time.perf_counter()
            for _ in range(n):
                stream.get()
            batches = stream.batches / (time.perf_counter() - t0)
        return inserts, batches
    finally:
        comp.stop()
