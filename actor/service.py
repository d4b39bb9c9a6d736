"""The actor: roll out episodes with the newest policy it has and publish each finished one.

On start it asks the learner for the latest weights (a late joiner must not wait
for the next broadcast), then follows the weights topic keeping only the newest
message (RingChannel(1): a slow actor never holds the learner back). It pauses
while the buffer says actors are ahead of the samples-per-insert ratio.
"""

from __future__ import annotations

import collections
import logging
import os
import time

import numpy as np
import zenoh

from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec, make_env
from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, session_config

from .policy import NumpyPolicy, initial_weights

log = logging.getLogger("actor")


class _Rollout:
    """The episode in progress in one env."""

    def __init__(self, obs: np.ndarray, version: int) -> None:
        self.obs = [obs]
        self.actions: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.version = version


def _fetch_weights(session: zenoh.Session, keys: P.Keys, wait_s: float, stop: StopFlag) -> P.Weights | None:
    """Ask the learner for its latest weights, waiting up to `wait_s` for it to be reachable.

    Right after a session opens, a query can find no queryable yet (discovery is
    asynchronous), so wait for the learner's queryable to match before asking.
    """
    querier = session.declare_querier(keys.weights, timeout=10.0)
    try:
        deadline = time.monotonic() + wait_s
        while not querier.matching_status.matching:
            if time.monotonic() > deadline or stop.wait(0.05):
                return None
        for reply in querier.get():
            if reply.ok is not None:
                try:
                    return P.decode_weights(reply.ok.payload.to_bytes())
                except P.ProtocolError as e:
                    log.warning("ignoring malformed weights reply: %s", e)
        return None
    finally:
        querier.undeclare()


def run_actor(cfg: Config, stop: StopFlag) -> int:
    spec = EnvSpec.of(cfg.env)
    keys = P.Keys(cfg.run)
    seed = cfg.seed + cfg.actor_id
    rng = np.random.default_rng(seed)
    incarnation = int.from_bytes(os.urandom(7), "little")
    envs = [make_env(cfg.env, cfg.actor_reward) for _ in range(cfg.envs_per_actor)]
    conf = session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)
    with open_session(conf) as session:
        weights_sub = session.declare_subscriber(keys.weights, zenoh.handlers.RingChannel(1))
        throttle_sub = session.declare_subscriber(keys.control_throttle, zenoh.handlers.RingChannel(1))
        session.declare_subscriber(keys.control_shutdown, lambda s: stop.set("shutdown message"))
        episodes_pub = session.declare_publisher(
            keys.episodes, congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA
        )
        stats_pub = session.declare_publisher(
            keys.stats_actor(cfg.actor_id),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_LOW,
        )
        token = session.liveliness().declare_token(keys.alive("actor", cfg.actor_id))

        weights = _fetch_weights(session, keys, cfg.weights_wait, stop)
        if weights is None:
            log.info("no learner answered; acting with a local random policy until weights arrive")
            weights = initial_weights(spec.obs_dim, spec.act_dim, cfg.hidden, seed)
        policy = NumpyPolicy(weights, spec.obs_dim, spec.act_dim)
        log.info("actor %d on %s with %d env(s), seed %d, policy version %d", cfg.actor_id, cfg.env, len(envs), seed,
                 policy.version)

        rollouts = []
        for j, env in enumerate(envs):
            obs, _ = env.reset(seed=seed + 10_000 * j)
            rollouts.append(_Rollout(np.asarray(obs, np.float32), policy.version))
        episodes = steps = seq = last_weights_poll = 0
        paused = False
        paused_s = 0.0
        waited_for_buffer_s = 0.0
        # publish-to-load delay of the last weights (same clock only on one machine)
        weights_latency_ms: collections.deque[float] = collections.deque(maxlen=100)
        last_return = None
        next_stats = time.monotonic()

        while not stop.is_set():
            msg = throttle_sub.try_recv()
            if msg is not None:
                try:
                    paused = bool(P.decode_control(msg.payload.to_bytes(), "throttle")["paused"])
                except (P.ProtocolError, KeyError):
                    log.warning("ignoring malformed throttle message")
            if paused:
                t0 = time.monotonic()
                stop.wait(0.01)
                paused_s += time.monotonic() - t0
            else:
                obs_batch = np.stack([r.obs[-1] for r in rollouts])
                acts = policy.sample(obs_batch, rng)
                env_acts = spec.to_env_action(acts)
                for j, (env, ro) in enumerate(zip(envs, rollouts)):
                    obs, reward, terminated, truncated, _ = env.step(env_acts[j])
                    ro.obs.append(np.asarray(obs, np.float32))
                    ro.actions.append(acts[j])
                    ro.rewards.append(float(reward))
                    steps += 1
                    if terminated or truncated:
                        rewards = np.asarray(ro.rewards, np.float32)
                        ep = P.Episode(
                            cfg.actor_id, seq, ro.version, float(rewards.sum(dtype=np.float64)),
                            bool(terminated), bool(truncated), np.stack(ro.obs), np.stack(ro.actions), rewards,
                            incarnation,
                        )
                        payload = P.EpisodeCodec.encode(ep)
                        # With no buffer service subscribed a put would vanish: hold the episode
                        # (and this actor) until one is back.
                        if not episodes_pub.matching_status.matching:
                            log.info("no buffer service is listening; holding episode %d until one is", seq)
                            t0 = time.monotonic()
                            while not episodes_pub.matching_status.matching and not stop.wait(0.05):
                                pass
                            waited_for_buffer_s += time.monotonic() - t0
                            if stop.is_set():
                                log.warning("stopping with episode %d unpublished (no buffer service)", seq)
                                break
                        episodes_pub.put(payload)
                        seq += 1
                        episodes += 1
                        last_return = ep.episode_return
                        obs, _ = env.reset()
                        rollouts[j] = _Rollout(np.asarray(obs, np.float32), policy.version)
            if paused or steps - last_weights_poll >= cfg.weights_poll_steps:
                # Paused actors keep polling, so they resume with the newest policy.
                last_weights_poll = steps
                msg = weights_sub.try_recv()
                if msg is not None:
                    try:
                        new = P.decode_weights(msg.payload.to_bytes())
                        if new.version > policy.version:
                            policy = NumpyPolicy(new, spec.obs_dim, spec.act_dim)
                            if new.sent_at:
                                weights_latency_ms.append(1000 * (time.time() - new.sent_at))
                    except P.ProtocolError as e:
                        log.warning("ignoring malformed weights: %s", e)
            now = time.monotonic()
            if now >= next_stats:
                stats_pub.put(
                    P.encode_stats(
                        {
                            "time": time.time(),
                            "actor_id": cfg.actor_id,
                            "episodes": episodes,
                            "steps": steps,
                            "policy_version": policy.version,
                            "paused": paused,
                            "paused_s": paused_s,
                            "waited_for_buffer_s": waited_for_buffer_s,
                            "weights_latency_ms_p50": float(np.median(weights_latency_ms)) if weights_latency_ms else None,
                            "last_episode_return": last_return,
                        }
                    )
                )
                next_stats = now + cfg.stats_interval
        token.undeclare()
        log.info("actor %d stopping (%s): %d episodes, %d steps", cfg.actor_id, stop.reason, episodes, steps)
    for env in envs:
        env.close()
    return 0
