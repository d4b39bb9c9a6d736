"""The buffer service's state without the network: D_O, D_E, the labeller, the rate limiter and the counters.

`ReplayState` builds the buffer's parts once and saves and restores them together; callers talk to
the parts: `intake` stores episodes (`ingest` a message, `store` a decoded one: `intake.py`), `sampler`
answers sample requests (`answer` a message, `sample` a decoded one: `sampler.py`).
What it keeps and how it labels follows the run's algorithm (`silcr.common.algorithms`):
D_E holds the agent's best episodes, or demonstrations, or nothing (`tables.py`); batches mix
D_E or not; the labeller writes the rewards. Unit tests and `silcr train --single-process`
use it directly; `service.run_buffer` serves it over Zenoh.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from silcr.common import run_layout, seeds
from silcr.common.algorithms import algorithm
from silcr.common.config import Config
from silcr.common.demos import load_demos
from silcr.common.envs import EnvSpec

from . import snapshot
from .intake import Intake
from .rate_limiter import SamplesPerInsertLimiter
from .sampler import Sampler
from .tables import Tables

log = logging.getLogger("buffer")


def reserved_bytes(cfg: Config, spec: EnvSpec) -> int:
    """The bytes D_O's and D_E's row storage reserves for `cfg`'s capacities and `spec`'s shapes.

    Mirrors `OnlineFifo` and `ExpertHeap`: observation and reward rows of float32, action rows
    (float32, or int64 indices), with their slack for whole episodes. Checked against the
    machine's memory before a run starts.
    """
    row = 4 * (spec.obs_dim + 1) + spec.action_bytes
    longest = min(spec.max_episode_steps or cfg.online_capacity, cfg.online_capacity)
    rows = cfg.online_capacity + cfg.online_capacity // 32 + 2 * (longest + 1)
    if algorithm(cfg.algo).ranks_own_episodes:
        rows += cfg.expert_capacity + cfg.expert_capacity // 8 + 2
    return rows * row


class ReplayState:
    """The buffer service without the network, in four parts that each save and restore themselves:
    the tables (`tables.Tables`: D_O, D_E, the labeller), the intake of episodes (`intake.Intake`), the
    answers to sample requests (`sampler.Sampler`) and the rate limiter between the two."""

    def __init__(self, cfg: Config, spec: EnvSpec) -> None:
        self.cfg = cfg
        self.spec = spec
        self.algo = algorithm(cfg.algo)
        self.tables = Tables(cfg, spec)
        # The tables by the paper's names, for the launchers and tests that look into them.
        self.fifo, self.heap, self.labeller = self.tables.fifo, self.tables.heap, self.tables.labeller
        self.limiter = SamplesPerInsertLimiter(
            cfg.samples_per_insert, cfg.learning_starts, cfg.spi_tolerance, throttle_inserts=not cfg.no_throttle,
            final_inserts=cfg.total_steps,
        )
        self.limits = spec.episode_limits(cfg.max_episode_bytes)
        self.rng = np.random.default_rng(seeds.buffer_sampling(cfg.seed))
        self.intake = Intake(self.tables, self.limiter, self.limits)
        self.sampler = Sampler(self.tables, self.intake, self.limiter, spec, self.rng)
        self.started = time.time()

    @property
    def transitions_received(self) -> int:
        """The env steps the buffer has stored: the run's step count."""
        return self.intake.transitions_received

    # -- checkpoints (`snapshot.Checkpointed`) -------------------------------------------------
    def identity(self) -> dict[str, str]:
        """What a checkpoint must match to be restored here."""
        return {"env": self.spec.env_id, "algo": self.algo.name}

    def activity(self) -> tuple[int, ...]:
        """What changes whenever the state does: episodes offered, sample requests answered."""
        return self.intake.episodes_received, sum(self.intake.rejections.values()), self.sampler.sample_requests

    def locks(self) -> tuple:
        return self.tables.locks()

    def parts(self) -> dict[str, Any]:
        return {"tables": self.tables, "intake": self.intake, "sampler": self.sampler, "limiter": self.limiter}

    def state(self) -> dict[str, Any]:
        """Everything a restart needs, by part (`snapshot` writes it)."""
        return {name: part.state() for name, part in self.parts().items()}

    def restore(self, state: dict[str, Any]) -> None:
        """Fill this fresh state from `state()`."""
        for name, part in self.parts().items():
            part.restore(state[name])

    # -- stats ------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        return {"time": time.time(), "uptime_s": time.time() - self.started, "run": self.cfg.run, "env": self.cfg.env,
                "algo": self.algo.name} | self.tables.stats() | self.intake.stats() | self.sampler.stats() | {
            "samples_per_insert": self.limiter.observed_samples_per_insert(),
            "samples_per_insert_target": self.limiter.samples_per_insert,
            "rate_limiter_error": self.limiter.error - self.limiter.centre,
            "warming_up": self.limiter.warming_up(),
        }


def checkpoint_path(cfg: Config) -> Path:
    return run_layout.buffer_checkpoint(cfg.run_dir)


def open_replay(cfg: Config, spec: EnvSpec) -> tuple[ReplayState, snapshot.Snapshot | None]:
    """The buffer's state, restored from its checkpoint with --resume when there is one (and that snapshot).

    Raises `snapshot.SnapshotError` for a checkpoint that cannot be used: a run
    refuses to start rather than silently begin empty (the file is kept for inspection).
    """
    state = ReplayState(cfg, spec)
    path = checkpoint_path(cfg)
    if not (cfg.resume and path.exists()):
        if cfg.resume:
            log.info("--resume: no buffer checkpoint at %s yet; starting empty", path)
        if cfg.expert_init:  # a restored D_E already holds what is left of them
            state.tables.warm_start(load_demos(Path(cfg.expert_init), spec))
        return state, None
    t0 = time.monotonic()
    snap = snapshot.restore(path, state)
    log.info("restored D_O (%d transitions) and D_E (%d) from %s in %.1fs; it was written %.0fs ago at %d "
             "transitions received; anything received after that was lost", len(state.fifo),
             len(state.heap) if state.heap is not None else 0, path, time.monotonic() - t0,
             time.time() - snap.header["written_at"], snap.transitions)
    return state, snap
