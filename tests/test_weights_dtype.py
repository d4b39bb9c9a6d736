"""Weights in float16 (`--weights-dtype float16`, protocol version 3; issue 20 item 2): half the bytes of every
publication, the actors' actions within 0.01 of float32's, older messages still read, and a run that uses them."""

from __future__ import annotations

import logging

import msgpack
import numpy as np
import pytest

from silcr.actor.policy import initial_weights, policy_for
from silcr.common import protocol as P
from silcr.common.envs import EnvSpec, make_env
from tests.helpers import LatestJson, Processes, client_when_up, free_port, wait_for

#: The largest difference allowed between an action from float16 weights and from float32 ones (actions in [-1, 1]).
#: Measured: 0.0035 and 0.0042 on two trained Swimmer policies (256-256), 0.0026 on the case below.
ACTION_TOLERANCE = 0.01


def _observations(env_id: str, n: int = 2000) -> np.ndarray:
    """Observations a random policy visits (the policies' inputs, at their real scale)."""
    env = make_env(env_id, "dense")
    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    out = []
    for _ in range(n):
        out.append(obs)
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    return np.asarray(out, np.float32)


def _over_the_wire(weights: P.Weights, dtype: str) -> P.Weights:
    weights.wire_dtype = dtype
    return P.Weights.decode(weights.encode())


def _weights(spec: EnvSpec, hidden: list[int], gain: float = 1.0) -> P.Weights:
    w = initial_weights(spec.obs_dim, spec.act_dim, hidden, seed=0, n_actions=spec.n_actions)
    w.version = 0
    w.params = {k: v * gain for k, v in w.params.items()}
    return w


def test_float16_weights_are_half_the_bytes_and_decode_to_float32():
    spec = EnvSpec.of("Hopper-v5")
    w = _weights(spec, [800, 400])
    full, half = len(_weights(spec, [800, 400]).encode()), None
    w.wire_dtype = "float16"
    half = len(w.encode())
    assert half / full < 0.51, (half, full)  # the paper's Hopper policy: 1.33 MB -> 0.66 MB per actor
    got = P.Weights.decode(w.encode())
    assert got.wire_dtype == "float16" and all(a.dtype == np.float32 for a in got.params.values())
    for k, a in w.params.items():
        np.testing.assert_allclose(got.params[k], a, rtol=1e-3, atol=1e-7)
    assert msgpack.unpackb(w.encode())["v"] == P.SCHEMA_VERSION == 3


@pytest.mark.parametrize("env_id, gain", [("Hopper-v5", 3.0), ("Humanoid-v5", 1.0)])
def test_actions_from_float16_weights_stay_within_the_tolerance_of_float32s(env_id, gain):
    """The paper's 800-400 policy on the observations a run sees; Hopper's weights scaled up three times
    (trained weights grow: the Swimmer policies' largest weight is 2.3-3.5, ten times the init's)."""
    spec = EnvSpec.of(env_id)
    obs = _observations(env_id)
    w32 = _weights(spec, [800, 400], gain)
    p32, p16 = policy_for(w32, spec), policy_for(_over_the_wire(_weights(spec, [800, 400], gain), "float16"), spec)
    diff = np.abs(np.stack([p32.deterministic(o) for o in obs]) - np.stack([p16.deterministic(o) for o in obs]))
    assert diff.max() <= ACTION_TOLERANCE, diff.max()
    assert diff.max() > 0  # the rounding is real: this is not comparing float32 with itself


def test_a_categorical_policy_from_float16_weights_picks_the_same_actions():
    spec = EnvSpec.of("MiniGrid-DoorKey-5x5-v0")
    obs = _observations(spec.env_id, 1000)
    w32 = _weights(spec, [128, 128], gain=3.0)
    p32, p16 = policy_for(w32, spec), policy_for(_over_the_wire(_weights(spec, [128, 128], 3.0), "float16"), spec)
    same = np.mean([p32.deterministic(o)[0] == p16.deterministic(o)[0] for o in obs])
    assert same >= 0.99, same


def test_a_weight_beyond_float16s_range_sends_that_publication_as_float32(caplog):
    spec = EnvSpec.of("Pendulum-v1")
    w = _weights(spec, [16, 16])
    first = next(iter(w.params))
    w.params[first] = w.params[first].copy()
    w.params[first].flat[0] = 1e6  # float16's largest is 65,504
    with caplog.at_level(logging.WARNING, logger="protocol"):
        got = _over_the_wire(w, "float16")
    assert got.wire_dtype == "float32" and got.params[first].flat[0] == 1e6
    assert "beyond float16's range" in caplog.text


def test_weights_of_version_2_are_read_and_a_bad_param_dtype_is_refused():
    spec = EnvSpec.of("Pendulum-v1")
    msg = msgpack.unpackb(_weights(spec, [16, 16]).encode())
    del msg["param_dtype"]
    msg["v"] = 2
    got = P.Weights.decode(msgpack.packb(msg))
    assert got.wire_dtype == "float32" and got.version == 0
    msg["v"], msg["param_dtype"] = 3, "<f8"
    with pytest.raises(P.ProtocolError) as e:
        P.Weights.decode(msgpack.packb(msg))
    assert e.value.reason == "bad_dtype" and "param_dtype" in str(e.value)


@pytest.mark.slow
def test_a_run_with_float16_weights_and_a_fanout_budget_reaches_its_actors(tmp_path):
    """Over Zenoh: the learner publishes half-size weights, the actors take them (none refused) and act on them.
    The same run checks the fan-out budget (tests/test_weights_fanout.py has its logic): at 0.5 MB/s for two
    actors the learner holds publications back, the traffic stays within the budget, and weights still flow."""
    procs = Processes(tmp_path)
    port, run = free_port(), "f16"
    keys = P.Keys(run)
    train = procs.start("train", "train", "--run", run, "--runs-dir", str(tmp_path / "runs"), "--zenoh-listen",
                        f"tcp/127.0.0.1:{port}", "--env", "InvertedPendulum-v5", "--hidden", "256", "256",
                        "--learning-starts", "500", "--batch-size", "64", "--eval-episodes", "1", "--stats-interval", "0.3",
                        "--total-steps", "3000", "--spi-tolerance", "200", "--actors", "2", "--weights-interval", "20",
                        "--weights-dtype", "float16", "--weights-fanout-mb-s", "0.5")
    try:
        session = client_when_up(port)  # kept: a session nothing refers to is closed, and its subscriber with it
        stats = LatestJson(session, keys.stats_all)
        wait_for(lambda: all((stats.get(keys.stats_actor(i)) or {}).get("policy_version", 0) > 2 for i in (0, 1)), 240,
                 "the actors to take published weights")
        first = stats.get(keys.stats_learner)
        wait_for(lambda: stats.get(keys.stats_learner)["weights_held"] > 10, 120, "the budget to hold publications back")
        learner = stats.get(keys.stats_learner)
        spec = EnvSpec.of("InvertedPendulum-v5")
        full = len(_weights(spec, [256, 256]).encode())
        assert learner["weights_bytes"] / full < 0.52, (learner["weights_bytes"], full)
        assert learner["weights_actors"] == 2 and learner["weights_fanout_budget_mb_s"] == 0.5
        # between two stats messages, publications x size x actors fit the budget (plus the one in flight)
        sent = (learner["weights_published"] - first["weights_published"]) * learner["weights_bytes"] * 2
        assert sent <= 0.5e6 * (learner["time"] - first["time"]) + learner["weights_bytes"] * 2, (first, learner)
        for i in (0, 1):
            assert stats.get(keys.stats_actor(i))["weights_rejected"] == 0
        session.close()
        assert train.wait(300) == 0, procs.log("train")
    finally:
        procs.stop_all()
    assert procs.orphans == []


def test_the_option_is_refused_with_one_line_when_misspelt(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "silcr.cli", "train", "--weights-dtype", "bfloat16", "--runs-dir",
                        str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--weights-dtype" in r.stderr and "Traceback" not in r.stderr
    assert not any(tmp_path.iterdir())


