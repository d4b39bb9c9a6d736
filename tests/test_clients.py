"""The protocol clients' own rules, in-process: weights versions and incarnations, unusable weights,
the in-process batch stream's ratio, buffer restarts, and zero-copy batches without warnings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from silcr.actor.policy import NumpyPolicy, initial_weights
from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.episode_channel import InProcessEpisodeWriter
from silcr.common.sample_channel import BatchStream, InProcessBatchStream
from silcr.common.weights_channel import InProcessWeights
from tests.conftest import make_episode

OBS, ACT = 4, 1


def _policy(w: P.Weights) -> NumpyPolicy:
    return NumpyPolicy(w, OBS, ACT)


def _weights(version: int, incarnation: int, seed: int = 0) -> P.Weights:
    w = initial_weights(OBS, ACT, [8], seed)
    return P.Weights(version, w.params, w.arch, incarnation=incarnation)


def test_actors_follow_a_restarted_learner_whose_versions_start_lower():
    """A learner restarted from an older checkpoint (or none) counts versions from there: a new incarnation wins."""
    board = InProcessWeights()
    board.publish(_weights(100, incarnation=1))
    client = board.client(_policy, initial_weights(OBS, ACT, [8], 9))
    assert client.version == 100
    board.publish(_weights(99, incarnation=1))  # older weights of the same learner: ignored
    assert not client.update() and client.version == 100
    board.publish(_weights(5, incarnation=2, seed=1))  # the restarted learner
    assert client.update() and client.version == 5 and client.weights.incarnation == 2
    np.testing.assert_array_equal(client.policy.layers[0][0], _weights(5, 2, seed=1).params["trunk.0.weight"].T)
    board.publish(_weights(6, incarnation=2, seed=2))
    assert client.update() and client.version == 6


@pytest.mark.parametrize("broken", ["log_std.weight", "log_std.bias", "mean.bias", "trunk.0.weight"])
def test_weights_with_a_misshapen_layer_are_rejected_and_counted(broken):
    board = InProcessWeights()
    client = board.client(_policy, _weights(1, incarnation=1))
    bad = _weights(2, incarnation=1)
    shape = bad.params[broken].shape
    bad.params[broken] = np.zeros((shape[0] + 1, *shape[1:]), np.float32)
    board.publish(bad)
    assert not client.update()  # no exception reaches the actor
    assert client.rejected == 1 and client.version == 1
    client.policy.sample(np.zeros((2, OBS), np.float32), np.random.default_rng(0))  # still acts


def _replay(**over) -> ReplayState:
    cfg = Config(run="t", env="InvertedPendulum-v5", learning_starts=20, batch_size=8, expert_capacity=200, **over)
    return ReplayState(cfg, EnvSpec.of("InvertedPendulum-v5"))


def test_the_in_process_stream_keeps_exactly_the_ratio():
    replay = _replay(samples_per_insert=0.5)
    writer = InProcessEpisodeWriter(replay.intake)
    stream = InProcessBatchStream(replay.sampler, P.SampleRequest(batches=4, batch_size=8))
    assert list(stream.due()) == [] and stream.not_ready == 1  # warming up: 20 transitions or fewer
    for seq, length in enumerate((10, 10, 10, 30, 7)):
        writer.write(make_episode(length, ret=1.0, seq=seq))
        for batch in stream.due():
            assert 1 <= batch.meta["batches"] <= 4
        # never ahead, never behind: half an update per transition after the first 20
        assert stream.batches == max(0, int((replay.transitions_received - 20) * 0.5))
    assert replay.transitions_received == 67 and stream.batches == 23 and replay.limiter.due() == 0


def test_the_limiter_takes_each_learner_s_count_from_its_first_request():
    """A learner restarted from an older checkpoint has made fewer updates than the buffer served: the
    limiter takes its count once, so those updates are served again; its later requests (whose counts lag
    the batches in flight) and requests without a count change nothing."""
    replay = _replay()
    for i in range(10):
        replay.intake.store(make_episode(10, ret=float(i), seq=i))  # 100 transitions: 80 updates due after 20
    first = P.SampleRequest(4, 8, learner=7, updates=0)
    assert replay.sampler.answer(first.encode()).meta["batches"] == 4 and replay.limiter.samples == 4
    replay.sampler.answer(P.SampleRequest(4, 8, learner=7, updates=1).encode())  # lagging count: ignored
    assert replay.limiter.samples == 8 and replay.sampler.limiter_realigned == 0
    # learner 9 restarted from a checkpoint at 2 updates: 6 served updates were lost with learner 7
    reply = replay.sampler.answer(P.SampleRequest(4, 8, learner=9, updates=2).encode())
    assert replay.limiter.samples == 2 + 4 and replay.sampler.limiter_realigned == 1 and reply.meta["batches"] == 4
    replay.sampler.answer(P.SampleRequest(4, 8).encode())  # no learner, no count: an old client
    assert replay.limiter.samples == 10 and replay.stats()["limiter_realigned"] == 1
    with pytest.raises(P.ProtocolError, match="'updates' is -1"):
        P.SampleRequest.decode(P._pack({"kind": "sample", "batches": 1, "batch_size": 8, "learner": 9, "updates": -1}))
    assert P.SampleRequest.decode(P.SampleRequest(1, 8, learner=9, updates=5).encode()).updates == 5
    assert P.SampleRequest.decode(P.SampleRequest(1, 8, learner=9).encode()).updates is None


def test_a_buffer_that_restarted_from_an_older_checkpoint_is_counted():
    stream = BatchStream()
    for steps in (100, 250, 180, 300):
        stream._account(P.BatchReply("not_ready", {"env_steps": steps}, reason="warmup"))
    assert stream.buffer_restarts == 1 and stream.transitions_lost == 70
    assert stream.not_ready == 4 and not stream.rate_limited
    stream._account(P.BatchReply("not_ready", {"env_steps": 300}, reason="rate_limited"))
    assert stream.rate_limited


def test_a_decoded_batch_trains_without_the_read_only_warning():
    """Decoded replies are read-only views of the message; the learner uses them without a copy or a warning."""
    from silcr.learner.update import to_tensor

    replay = _replay()
    for i in range(5):
        replay.intake.store(make_episode(10, ret=float(i), seq=i))
    reply = P.BatchReply.decode(replay.sampler.sample(P.SampleRequest(2, 8)).encode())
    assert not reply.batch.obs.flags.writeable
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t = reply.batch.map(lambda a: to_tensor(a, torch.device("cpu")))
    assert t.obs.data_ptr() == reply.batch.obs.ctypes.data  # the same memory: no copy
    assert t.obs.shape == (16, OBS)


def test_a_paused_writer_sleeps_until_the_buffer_lets_it_go_on():
    """Paused actors wait on the throttle notice instead of polling it (128 paced actors polling every
    10 ms took the learner's cores); the wait ends with the notice, and a malformed one changes nothing."""
    import threading
    import time

    from silcr.common.control_channel import Throttle
    from silcr.common.episode_channel import ZenohEpisodeWriter
    from silcr.common.lifecycle import StopFlag
    from silcr.common.zenoh_session import open_session, router_config, session_config
    from tests.helpers import free_port, wait_for

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    keys = P.Keys("throttle-wait")
    with open_session(router_config([endpoint])), \
            open_session(session_config([endpoint], mode="client")) as actor_side, \
            open_session(session_config([endpoint], mode="client")) as buffer_side:
        writer = ZenohEpisodeWriter(actor_side, keys, StopFlag(), actor_id=0, incarnation=1)
        throttle = Throttle(buffer_side, keys)
        assert writer.wait_unpaused(0.0)  # not paused before any notice
        wait_for(lambda: throttle._pub.matching_status.matching, 20, "the actor's subscription")
        throttle.send(True)
        wait_for(writer.paused, 10, "the pause notice")
        t0 = time.monotonic()
        assert not writer.wait_unpaused(0.3)  # still paused: the wait runs its course
        assert time.monotonic() - t0 >= 0.25
        buffer_side.put(keys.control_throttle, b"\xc1garbage")
        wait_for(lambda: writer.throttle_rejections, 10, "the malformed notice to be counted")
        assert writer.paused()
        threading.Timer(0.2, throttle.send, (False,)).start()
        t0 = time.monotonic()
        assert writer.wait_unpaused(20)
        assert not writer.paused() and time.monotonic() - t0 < 10


def test_a_malformed_weights_message_is_counted_even_when_a_newer_set_replaces_it_unread():
    """The actor takes only the newest weights; a bad message that a good one follows before the actor
    looks (a paused actor looks every 0.25 s) is still counted, as it arrives."""
    from silcr.common.lifecycle import StopFlag
    from silcr.common.weights_channel import ZenohWeightsClient
    from silcr.common.zenoh_session import open_session, router_config, session_config
    from tests.helpers import free_port, wait_for

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    keys = P.Keys("weights-superseded")
    with open_session(router_config([endpoint])), \
            open_session(session_config([endpoint], mode="client")) as actor_side, \
            open_session(session_config([endpoint], mode="client")) as learner_side:
        client = ZenohWeightsClient(actor_side, keys, _policy, lambda: _weights(0, incarnation=1), 0.0, StopFlag())
        pub = learner_side.declare_publisher(keys.weights)
        wait_for(lambda: pub.matching_status.matching, 20, "the actor's subscription")
        pub.put(b"\xc1 not weights")
        pub.put(_weights(7, incarnation=1).encode())
        wait_for(lambda: client.rejections, 10, "the malformed message to be counted")
        wait_for(client.update, 10, "the good weights")
        assert client.version == 7 and sum(client.rejections.values()) == 1
