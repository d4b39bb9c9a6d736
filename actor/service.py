"""The actor: roll out episodes with the newest policy it has and write each finished one.

`Actor` is the rollout alone: its envs and episodes in progress, stepped one batched
forward pass at a time, writing finished episodes through an `EpisodeWriter` and
acting with a `WeightsClient`'s policy (silcr.common.weights_channel). `run_actor` is the
process around it over Zenoh: wait while no buffer service listens, pause while the
buffer's rate limiter says actors are ahead, take new weights every `--weights-poll-steps`
steps, publish stats.
`silcr train --single-process` steps the same `Actor` with in-process clients.
"""

from __future__ import annotations

import logging
import socket
import time

import numpy as np

from silcr.common import protocol as P
from silcr.common import seeds
from silcr.common.config import Config
from silcr.common.control_channel import finished_reason
from silcr.common.envs import EnvSpec, make_env
from silcr.common.episode_channel import EpisodeWriter, ZenohEpisodeWriter
from silcr.common.lifecycle import StopFlag
from silcr.common.presence import Presence
from silcr.common.role_session import role_session
from silcr.common.weights_channel import WeightsClient, ZenohWeightsClient

from .policy import Policy, initial_weights, usable_policy

log = logging.getLogger("actor")
#: The machine an actor runs on, in its stats (which node of a cluster, which host of several).
HOST = socket.gethostname()
# A paused actor wakes this often (unless the buffer lets it go on first) to take newer weights
# and publish its stats.
PAUSED_POLL_S = 0.25
#: How long a stopping actor waits for the buffer to confirm its last episodes (none when the run finished).
CLOSE_WAIT_S = 5.0


class _Rollout:
    """The episode in progress in one env."""

    def __init__(self, obs: np.ndarray, version: int) -> None:
        self.obs = [obs]
        self.actions: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.version = version


def policy_factory(spec: EnvSpec):
    """Weights -> the actors' NumPy policy for `spec` (raises ProtocolError for weights that do not fit, or whose
    forward pass overflows: `policy.usable_policy`)."""
    return lambda w: usable_policy(w, spec)


def random_initial_weights(cfg: Config, spec: EnvSpec, seed: int):
    """The untrained policy an actor acts with until the learner's weights arrive."""
    return lambda: initial_weights(spec.obs_dim, spec.act_dim, cfg.hidden, seed, spec.n_actions)


class Actor:
    """`envs_per_actor` envs stepped together with one batched forward pass of the current policy."""

    def __init__(self, cfg: Config, spec: EnvSpec, actor_id: int, writer: EpisodeWriter,
                 weights: WeightsClient[Policy], incarnation: int | None = None) -> None:
        self.actor_id = actor_id
        self.seed = seeds.actor(cfg.seed, actor_id)
        self.spec = spec
        self.writer = writer
        self.weights = weights
        self.rng = np.random.default_rng(self.seed)
        self.incarnation = P.new_incarnation() if incarnation is None else incarnation
        self.envs = [make_env(cfg.env, cfg.actor_reward) for _ in range(cfg.envs_per_actor)]
        self.rollouts = []
        for j, env in enumerate(self.envs):
            obs, _ = env.reset(seed=seeds.actor_env(self.seed, j))
            self.rollouts.append(_Rollout(np.asarray(obs, np.float32), weights.version))
        self.episodes = self.steps = self.seq = 0
        self.last_return: float | None = None

    def step(self) -> bool:
        """One step of every env; finished episodes are written. False if a write gave up (stopping)."""
        obs = np.stack([r.obs[-1] for r in self.rollouts])
        with np.errstate(over="ignore", invalid="ignore"):
            acts = self.weights.policy.sample(obs, self.rng)
        if not np.isfinite(acts).all():
            # Weights that passed their probe but overflow on these observations: never act with NaN (the
            # episode would be refused whole); back to the last good policy, counted (`weights_rejections`).
            self.weights.fall_back("non_finite_actions")
            acts = self.weights.policy.sample(obs, self.rng)
        env_acts = self.spec.to_env_action(acts)
        for j, (env, ro) in enumerate(zip(self.envs, self.rollouts)):
            obs, reward, terminated, truncated, _ = env.step(env_acts[j])
            ro.obs.append(np.asarray(obs, np.float32))
            ro.actions.append(acts[j])
            ro.rewards.append(float(reward))
            self.steps += 1
            if terminated or truncated:
                rewards = np.asarray(ro.rewards, np.float32)
                ep = P.Episode(self.actor_id, self.seq, ro.version, float(rewards.sum(dtype=np.float64)),
                               bool(terminated), bool(truncated), np.stack(ro.obs), np.stack(ro.actions), rewards,
                               self.incarnation)
                if not self.writer.write(ep):
                    return False
                self.seq += 1
                self.episodes += 1
                self.last_return = ep.episode_return
                obs, _ = env.reset()
                self.rollouts[j] = _Rollout(np.asarray(obs, np.float32), self.weights.version)
        return True

    def stats(self) -> dict:
        return {"actor_id": self.actor_id, "host": HOST, "episodes": self.episodes, "steps": self.steps,
                "last_episode_return": self.last_return} | self.writer.stats() | self.weights.stats()

    def close(self) -> None:
        for env in self.envs:
            env.close()


def run_actor(cfg: Config, stop: StopFlag) -> int:
    seed = seeds.actor(cfg.seed, cfg.actor_id)
    with role_session(cfg, stop, "actor", cfg.actor_id) as role:
        incarnation = P.new_incarnation()
        writer = ZenohEpisodeWriter(role.session, role.keys, stop, cfg.actor_id, incarnation,
                                    int(cfg.actor_outbox_mb * 2**20))
        weights = ZenohWeightsClient(role.session, role.keys, policy_factory(role.spec),
                                     random_initial_weights(cfg, role.spec, seed), cfg.weights_wait, stop)
        # Logs when the buffer leaves and comes back (its stats say it too: `waiting_for_buffer`).
        Presence.buffer(role.session, role.keys, stop)
        actor = Actor(cfg, role.spec, cfg.actor_id, writer, weights, incarnation)
        log.info("actor %d on %s with %d env(s), seed %d, policy version %d", cfg.actor_id, cfg.env, len(actor.envs),
                 seed, weights.version)
        paused_s = 0.0
        last_poll = 0
        while not stop.is_set():
            # Steps taken while no buffer listens would end in an episode held until one does: wait
            # before stepping instead, awake (stats, weights) rather than blocked in a write.
            waiting = not writer.buffer_listening()
            paused = writer.paused()
            full = writer.outbox_full()
            if waiting:
                writer.wait_for_buffer(PAUSED_POLL_S)
            elif full:
                # Episodes the buffer has not confirmed fill the outbox (a cut link, a slow buffer):
                # wait for its acks, sending again what is due, rather than step on and lose some.
                writer.wait_for_room(PAUSED_POLL_S)
            elif paused:
                # Back at once when the buffer says so; otherwise awake every PAUSED_POLL_S
                # to take newer weights and publish stats.
                t0 = time.monotonic()
                writer.wait_unpaused(PAUSED_POLL_S)
                paused_s += time.monotonic() - t0
            elif not actor.step():
                break
            else:
                writer.pump()  # what an ack asked for again, or what timed out
            if waiting or paused or full or actor.steps - last_poll >= cfg.weights_poll_steps:
                # Waiting actors keep polling, so they go on with the newest policy.
                last_poll = actor.steps
                weights.update()
            if role.stats_due.due():
                role.stats.put({"time": time.time(), "paused": paused, "paused_s": paused_s,
                                "waiting_for_buffer": waiting} | actor.stats())
        # What the buffer has not confirmed yet gets a moment; the rest is counted as not written.
        writer.close(timeout=0.0 if stop.reason == finished_reason() else CLOSE_WAIT_S)
        written = writer.stats()
        log.info("actor %d on %s stopping (%s): %d episodes, %d steps; %d episodes written to the buffer, %d not",
                 cfg.actor_id, HOST, stop.reason, actor.episodes, actor.steps, written["episodes_written"],
                 written["episodes_unwritten"])
    actor.close()
    return 0
