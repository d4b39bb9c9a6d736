"""The buffer service as a real process behind a real Zenoh router: the test plays actor and learner."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zenoh

from silcr.common import protocol as P
from tests.conftest import make_episode
from tests.helpers import LatestJson, Processes, client_when_up, free_port, wait_for

RUN = "itest-buffer"
KEYS = P.Keys(RUN)
LEARNER = 4242  # the incarnation this test's learner token declares: the buffer serves only live learners
ENV, OBS, ACT = "silcr/PointGoal-v0", 3, 2


def episode(length: int, **kw) -> P.Episode:
    return make_episode(length, obs_dim=kw.pop("obs_dim", OBS), act_dim=ACT, **kw)
REQUIRED_STATS = {
    "online_transitions", "online_capacity", "online_evicted", "online_evicted_for_rows", "expert_transitions",
    "expert_capacity", "expert_episodes",
    "expert_min_return", "expert_max_return", "episodes_received", "transitions_received", "episodes_rejected",
    "batches_served", "samples_per_insert",
}


@pytest.fixture(scope="module")
def system(tmp_path_factory):
    port = free_port()
    procs = Processes(tmp_path_factory.mktemp("buffer-logs"))
    ep = f"tcp/127.0.0.1:{port}"
    procs.start("router", "router", "--listen", ep)
    procs.start(
        # PointGoal's episodes last 50 steps: M may be as small as that (5 of the test's 10-step episodes)
        "buffer", "buffer", "--run", RUN, "--env", ENV, "--connect", ep,
        "--learning-starts", "50", "--expert-capacity", "50", "--spi-tolerance", "1000", "--stats-interval", "0.2",
    )
    session = client_when_up(port)
    token = session.liveliness().declare_token(KEYS.alive("learner", LEARNER))
    stats = LatestJson(session, KEYS.stats_all)
    wait_for(lambda: stats.get(KEYS.stats_buffer), 30, "buffer stats")
    yield procs, session, stats
    token.undeclare()
    session.close()
    procs.stop_all()


def _publish(session, payloads):
    pub = session.declare_publisher(KEYS.episodes, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_for(lambda: pub.matching_status.matching, 10, "the buffer's episode subscriber")
    for p in payloads:
        pub.put(p)
    pub.undeclare()


def _query(session, payload):
    replies = list(session.get(KEYS.sample, payload=payload, timeout=10))
    assert len(replies) == 1
    return replies[0]


def test_stats_are_json_with_the_contract_fields(system):
    _, _, stats = system
    s = stats.get(KEYS.stats_buffer)
    assert REQUIRED_STATS <= s.keys()
    assert stats.encodings[KEYS.stats_buffer].startswith("application/json")
    assert s["online_capacity"] == 1_000_000 and s["expert_capacity"] == 50


def test_not_ready_during_warmup(system):
    _, session, _ = system
    r = _query(session, P.SampleRequest(1, 8, learner=LEARNER).encode())
    reply = P.BatchReply.decode(r.ok.payload.to_bytes())
    assert reply.status == "not_ready" and reply.reason == "warmup"


def test_episodes_arrive_bad_ones_are_rejected_and_batches_are_mixed(system):
    procs, session, stats = system
    good = [episode(10, ret=float(i), seq=i, start=1000 * i).encode() for i in range(10)]
    wrong_dim = episode(10, obs_dim=7).encode()
    nan = msgpack.unpackb(good[0], raw=False)
    arr = np.frombuffer(nan["obs"][2], np.float32).copy()
    arr[3] = np.nan
    nan["obs"][2] = arr.tobytes()
    bad = [b"garbage", wrong_dim, msgpack.packb(nan, use_bin_type=True)]
    _publish(session, good[:5] + bad + good[5:])

    s = wait_for(lambda: (x := stats.get(KEYS.stats_buffer)) and x["episodes_received"] + x["episodes_rejected"] >= 13 and x,
                 20, "13 episodes to be counted")
    assert s["episodes_received"] == 10 and s["transitions_received"] == 100
    assert s["episodes_rejected"] == 3
    assert s["rejections"] == {"not_msgpack": 1, "obs_dim": 1, "non_finite": 1}
    # D_E holds the best whole episodes within M = 50: returns 5..9
    assert s["expert_episodes"] == 5 and s["expert_min_return"] == 5.0 and s["expert_max_return"] == 9.0
    assert procs.procs["buffer"].poll() is None

    r = _query(session, P.SampleRequest(2, 16, learner=LEARNER).encode())
    reply = P.BatchReply.decode(r.ok.payload.to_bytes())
    assert reply.status == "ok" and reply.meta["batches"] == 2
    rewards = reply.batch.rewards.reshape(2, 16)
    np.testing.assert_array_equal(rewards[:, :8], 0.0)
    np.testing.assert_array_equal(rewards[:, 8:], 1.0)
    expert_obs = reply.batch.obs.reshape(2, 16, OBS)[:, 8:, 0]
    assert (expert_obs >= 5000).all()  # only the top episodes are in D_E
    np.testing.assert_array_equal(reply.batch.next_obs[:, 0], reply.batch.obs[:, 0] + 1)


def test_bad_sample_requests_get_an_error_reply_and_the_service_lives(system):
    procs, session, stats = system
    for payload in (b"junk", msgpack.packb({"v": P.SCHEMA_VERSION, "batches": 0, "batch_size": 8}), None):
        r = _query(session, payload)
        assert r.err is not None
        assert r.err.payload.to_string().split(":")[0] in {"not_msgpack", "bad_request"}
    # legal requests from no learner, or from one that is not alive: refused, so they spend none of its budget
    for stranger in (P.SampleRequest(1, 8), P.SampleRequest(1, 8, learner=LEARNER + 1)):
        r = _query(session, stranger.encode())
        assert r.err is not None and r.err.payload.to_string().startswith("not_the_learner:")
    r = _query(session, P.SampleRequest(1, 8, learner=LEARNER).encode())
    assert P.BatchReply.decode(r.ok.payload.to_bytes()).status == "ok"
    s = wait_for(lambda: (x := stats.get(KEYS.stats_buffer)) and x["sample_requests_rejected"] >= 5 and x, 10, "stats")
    assert s["sample_requests_rejected"] == 5 and s["episodes_received"] == 10
    assert s["request_rejections"]["not_the_learner"] == 2
    assert procs.procs["buffer"].poll() is None
