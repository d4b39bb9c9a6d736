"""Actors under bad weights (issue 42, items 2 and 3): weights whose forward pass overflows are refused before
use and the actor keeps acting with its last good policy (no stall, no dropped or refused episode), and a flood
of rejected weights logs one grouped line per reason, not one per message."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from silcr.actor.policy import initial_weights
from silcr.actor.service import Actor, policy_factory
from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.episode_channel import InProcessEpisodeWriter
from silcr.common.weights_channel import InProcessWeights
from tests.helpers import LatestJson, Processes, client_when_up, free_port, wait_for

ENV = "InvertedPendulum-v5"
HIDDEN = [16, 16]


def _huge(spec: EnvSpec, version: int, value: float = 3e38, incarnation: int = 0) -> P.Weights:
    """Finite weights (they pass the wire's check) whose forward pass overflows float32."""
    w = initial_weights(spec.obs_dim, spec.act_dim, HIDDEN, 1)
    return P.Weights(version, {k: np.full_like(v, value) for k, v in w.params.items()}, w.arch, incarnation=incarnation)


def _actor():
    cfg = Config(run="guard", env=ENV, hidden=HIDDEN, expert_capacity=1000)
    spec = EnvSpec.of(ENV)
    replay = ReplayState(cfg, spec)
    board = InProcessWeights()
    good = initial_weights(spec.obs_dim, spec.act_dim, HIDDEN, 0)
    good.version = 3
    return spec, replay, board, Actor(cfg, spec, 0, InProcessEpisodeWriter(replay.intake), board.client(policy_factory(spec), good))


def test_weights_that_overflow_are_refused_and_the_actor_keeps_its_policy():
    spec, replay, board, actor = _actor()
    board.publish(_huge(spec, 5))
    assert not actor.weights.update()  # refused before any step is taken with them
    assert actor.weights.version == 3 and actor.weights.rejections == {"non_finite_output": 1}
    for _ in range(500):
        actor.step()
    assert replay.intake.episodes_received > 20 and not replay.intake.rejections  # episodes go on, none refused
    assert all(np.isfinite(e.actions).all() for e in replay.fifo.episodes())
    assert {e.policy_version for e in replay.fifo.episodes()} == {3}


def test_weights_that_pass_the_probe_but_overflow_in_use_are_dropped_for_the_last_good_ones(monkeypatch):
    """A probe cannot try every observation: actions that come out NaN send the actor back to its previous
    policy, and those weights are never taken again."""
    import silcr.actor.policy as policy

    monkeypatch.setattr(policy, "probe_observations", lambda obs_dim: np.zeros((1, obs_dim), np.float32))
    spec, replay, board, actor = _actor()
    w = initial_weights(spec.obs_dim, spec.act_dim, HIDDEN, 1)
    signs = np.random.default_rng(0)
    params = {k: (3e38 * signs.choice([-1.0, 1.0], v.shape).astype(np.float32) if k.endswith("weight")
                  else np.zeros_like(v)) for k, v in w.params.items()}
    board.publish(P.Weights(7, params, w.arch))  # zero biases: 0 at the zero observation, inf - inf (NaN) elsewhere
    assert actor.weights.update() and actor.weights.version == 7
    for _ in range(300):
        actor.step()
    assert actor.weights.version == 3 and actor.weights.rejections["non_finite_actions"] == 1
    assert not actor.weights.update()  # the same weights are not taken again
    assert replay.intake.episodes_received > 10 and not replay.intake.rejections
    assert all(np.isfinite(e.actions).all() for e in replay.fifo.episodes())


def test_a_flood_of_rejected_weights_logs_one_line_per_reason(caplog):
    spec, replay, board, actor = _actor()
    caplog.set_level(logging.WARNING, logger="clients")
    for v in range(10, 310):
        board.publish(_huge(spec, v))
        actor.weights.update()
    assert actor.weights.rejections["non_finite_output"] == 300
    lines = [r for r in caplog.records if "weights" in r.getMessage()]
    assert len(lines) == 1 and "1 rejected for non_finite_output so far" in lines[0].getMessage()


@pytest.mark.slow
def test_a_distributed_run_under_a_flood_of_overflowing_weights_keeps_storing_episodes(tmp_path):
    procs = Processes(tmp_path)
    port, run = free_port(), "flood"
    keys = P.Keys(run)
    spec = EnvSpec.of(ENV)
    train = procs.start("train", "train", "--run", run, "--runs-dir", str(tmp_path / "runs"),
                        "--zenoh-listen", f"tcp/127.0.0.1:{port}", "--env", ENV, "--hidden", *map(str, HIDDEN),
                        "--learning-starts", "500", "--batch-size", "64", "--actors", "2", "--total-steps", "8000",
                        "--eval-interval", "4000", "--eval-episodes", "2", "--stats-interval", "0.3",
                        "--no-throttle")  # actors never paused by the ratio: a stall could only be the weights'
    session = None
    try:
        session = client_when_up(port)
        stats = LatestJson(session, keys.stats_all)
        wait_for(lambda: (stats.get(keys.stats_learner) or {}).get("updates", 0) > 0, 120, "training to start")
        before = stats.get(keys.stats_buffer)["episodes_received"]
        sent, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < 4.0:  # every 20 ms for 4 s, each newer than the learner's
            session.put(keys.weights, _huge(spec, 10**6 + sent, incarnation=12345).encode())
            sent += 1
            time.sleep(0.02)
        during = stats.get(keys.stats_buffer)["episodes_received"]
        assert during > before, "no episode reached the buffer while the weights were published"
        actors = [stats.get(keys.stats_actor(i)) or {} for i in (0, 1)]
        assert all(a.get("weights_rejections", {}).get("non_finite_output", 0) >= 1 for a in actors), actors
        assert train.wait(600) == 0, procs.log("train")
    finally:
        procs.stop_all()
        if session is not None:
            session.close()
    assert procs.orphans == []
    buffer_stats = stats.get(keys.stats_buffer)
    assert buffer_stats["rejections"].get("non_finite", 0) == 0  # no episode of NaN actions was ever sent
    for i in (0, 1):
        log = (tmp_path / "runs" / run / "logs" / f"actor-{i}.log").read_text()
        assert log.count("non_finite_output") <= 2, log[-2000:]  # grouped: at most one line per 10 s
    assert sent > 150
