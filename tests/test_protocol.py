"""The wire schema: round trips and every rejection, plus a property-based decoder test."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from silcr.common import protocol as P
from tests.conftest import make_episode

LIMITS = P.EpisodeLimits(obs_dim=4, act_dim=1, max_steps=1000, max_bytes=1 << 20)


def _raw(ep: P.Episode) -> dict:
    return msgpack.unpackb(ep.encode(), raw=False)


def _pack(msg: dict) -> bytes:
    return msgpack.packb(msg, use_bin_type=True)


def test_episode_round_trip():
    ep = make_episode(7, ret=3.5, actor_id=2, seq=9, version=4, terminated=False, truncated=True)
    back = P.Episode.decode(ep.encode(), LIMITS)
    assert (back.actor_id, back.seq, back.policy_version) == (2, 9, 4)
    assert back.episode_return == pytest.approx(3.5)
    assert (back.terminated, back.truncated) == (False, True)
    np.testing.assert_array_equal(back.obs, ep.obs)
    np.testing.assert_array_equal(back.actions, ep.actions)
    np.testing.assert_array_equal(back.rewards, ep.rewards)
    assert back.length == 7 and back.obs.shape == (8, 4)


def _mutate(**changes):
    msg = _raw(make_episode(5, ret=1.0))
    for k, v in changes.items():
        if v is KeyError:
            del msg[k]
        else:
            msg[k] = v
    return _pack(msg)


BAD_ARRAY_F64 = P.pack_array(np.zeros((6, 4), np.float64))
NAN_OBS = np.zeros((6, 4), np.float32)
NAN_OBS[2, 1] = np.nan


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\xc1\xff not msgpack", "not_msgpack"),
        (msgpack.packb([1, 2, 3]), "not_a_map"),
        (_mutate(v=99), "schema_version"),
        (_mutate(v=KeyError), "schema_version"),
        (_mutate(obs=KeyError), "missing_field"),
        (_mutate(actor_id="zero"), "bad_field"),
        (_mutate(terminated=1), "bad_field"),
        (_mutate(obs=BAD_ARRAY_F64), "bad_dtype"),
        (_mutate(obs=["<f4", [6, 4], b"\x00" * 10]), "bad_shape"),
        (_mutate(obs=P.pack_array(np.zeros((6, 5), np.float32))), "obs_dim"),
        (_mutate(actions=P.pack_array(np.zeros((5, 2), np.float32))), "act_dim"),
        (_mutate(obs=P.pack_array(np.zeros((5, 4), np.float32))), "length_mismatch"),
        (_mutate(length=0), "empty"),
        (_mutate(length=5000), "too_long"),
        (_mutate(obs=P.pack_array(NAN_OBS)), "non_finite"),
        (_mutate(episode_return=float("inf")), "non_finite"),
        (_mutate(actions=P.pack_array(np.full((5, 1), 3.0, np.float32))), "action_range"),
        (_mutate(episode_return=123.0), "return_mismatch"),
        (_mutate(terminated=False, truncated=False), "not_finished"),
        (_mutate(kind="weights"), "bad_field"),
        (b"\x00" * ((1 << 20) + 1), "oversized"),
    ],
)
def test_episode_rejections(payload, reason):
    with pytest.raises(P.ProtocolError) as info:
        P.Episode.decode(payload, LIMITS)
    assert info.value.reason == reason
    assert str(info.value)  # a human-readable one-line explanation
    assert "\n" not in str(info.value)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2048))
def test_decoder_never_crashes_on_random_bytes(data):
    try:
        P.Episode.decode(data, LIMITS)
    except P.ProtocolError:
        pass


_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**63 - 1) | st.floats() | st.text(max_size=8) | st.binary(max_size=64),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(sorted(_raw(make_episode(3)).keys())), _values, max_size=12))
def test_decoder_rejects_structured_garbage_cleanly(fields):
    msg = _raw(make_episode(3, ret=1.0)) | fields
    try:
        ep = P.Episode.decode(_pack(msg), LIMITS)
    except P.ProtocolError:
        return
    # Anything accepted must be internally consistent.
    assert ep.obs.shape == (ep.length + 1, 4) and ep.actions.shape == (ep.length, 1)
    assert np.isfinite(ep.obs).all()


def test_weights_round_trip_and_rejection():
    w = P.Weights(7, {"a.weight": np.ones((2, 3), np.float32)}, {"hidden": [3]})
    back = P.Weights.decode(w.encode())
    assert back.version == 7 and back.arch == {"hidden": [3]}
    np.testing.assert_array_equal(back.params["a.weight"], np.ones((2, 3)))
    bad = P.Weights(1, {"a": np.array([np.nan], np.float32)})
    with pytest.raises(P.ProtocolError, match="NaN"):
        P.Weights.decode(bad.encode())


@pytest.mark.parametrize("batches, batch_size", [(0, 128), (65, 128), (1, 1), (1, 10**6)])
def test_sample_request_bounds(batches, batch_size):
    raw = msgpack.packb({"v": P.SCHEMA_VERSION, "kind": "sample", "batches": batches, "batch_size": batch_size})
    with pytest.raises(P.ProtocolError) as info:
        P.SampleRequest.decode(raw)
    assert info.value.reason == "bad_request"


def test_sample_request_and_batch_reply_round_trip():
    assert P.SampleRequest.decode(P.SampleRequest(3, 64).encode()) == P.SampleRequest(3, 64)
    n = 4
    batch = P.Batch(obs=np.zeros((n, 2)), actions=np.zeros((n, 1)), rewards=np.arange(n), next_obs=np.ones((n, 2)),
                    terminated=np.array([0, 1, 0, 0]), truncated=np.zeros(n), policy_version=np.arange(n))
    back = P.BatchReply.decode(P.BatchReply("ok", {"env_steps": 5, "batches": 2, "batch_size": 2}, batch).encode())
    assert back.status == "ok" and back.meta["env_steps"] == 5 and back.disc is None
    assert back.batch.obs.dtype == np.float32 and back.batch.terminated.dtype == np.uint8
    np.testing.assert_array_equal(back.batch.rewards, [0, 1, 2, 3])
    nr = P.BatchReply.decode(P.BatchReply("not_ready", {}, reason="warmup", retry_after_ms=50).encode())
    assert (nr.status, nr.reason, nr.retry_after_ms) == ("not_ready", "warmup", 50)


@pytest.mark.parametrize("name", ["ok", "Hopper-v5-silcr-20261122", "a.b_c"])
def test_valid_run_names(name):
    assert P.Keys(name).episodes == f"silcr/{name}/episodes"


@pytest.mark.parametrize("name", ["", "a/b", "run*", "x?y", "$x", "a#b", "é"])
def test_invalid_run_names(name):
    with pytest.raises(ValueError):
        P.Keys(name)


def test_key_contract():
    k = P.Keys("r1")
    assert k.stats_buffer == "silcr/r1/stats/buffer"
    assert k.stats_learner == "silcr/r1/stats/learner"
    assert k.stats_actor(3) == "silcr/r1/stats/actor/3"
    assert (k.episodes, k.weights, k.sample) == ("silcr/r1/episodes", "silcr/r1/weights", "silcr/r1/sample")
    assert k.alive("actor", 2) == "silcr/r1/alive/actor/2"


# --- every decoder, fuzzed: a message decodes to something every later stage can store and use,
# --- or the decoder raises ProtocolError, and nothing else happens ---------------------------------

MSGPACK_INTS = st.integers(-(2**63), 2**64 - 1)  # everything msgpack can carry
_hostile = st.recursive(
    st.none() | st.booleans() | MSGPACK_INTS | st.sampled_from([2**63, 2**64 - 1, -(2**63), -1, 0])
    | st.floats() | st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e308]) | st.text(max_size=8)
    | st.binary(max_size=64),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@pytest.fixture(scope="module")
def replay():
    from silcr.buffer_service.replay import ReplayState
    from silcr.common.config import Config
    from silcr.common.envs import EnvSpec

    state = ReplayState(Config(run="fuzz", env="InvertedPendulum-v5", algo="gasil", learning_starts=10,
                               expert_capacity=1000, online_capacity=5000), EnvSpec.of("InvertedPendulum-v5"))
    for i in range(20):
        state.intake.store(make_episode(10, ret=float(i), seq=i, start=100 * i))
    return state


def _mutated(valid: bytes, fields: dict) -> bytes:
    msg = msgpack.unpackb(valid, raw=False) | fields
    return msgpack.packb(msg, use_bin_type=True)


def _fuzz(valid: bytes, decode, use):
    """Random bytes, and the valid message with fields replaced by hostile values."""
    keys = sorted(msgpack.unpackb(valid, raw=False))

    @settings(max_examples=250, deadline=None)
    @given(st.one_of(st.binary(max_size=512).map(lambda b: (b, None)),
                     st.dictionaries(st.sampled_from(keys), _hostile, max_size=6).map(lambda f: (None, f))))
    def run(case):
        raw, fields = case
        payload = raw if raw is not None else _mutated(valid, fields)
        try:
            obj = decode(payload)
        except P.ProtocolError:
            return
        use(obj)

    run()


def test_fuzzed_episodes_are_storable_or_rejected(replay):
    from silcr.buffer_service.replay import ReplayState
    from silcr.common.config import Config
    from silcr.common.envs import EnvSpec

    def use(ep):
        fresh = ReplayState(Config(run="f", env="InvertedPendulum-v5", learning_starts=0, expert_capacity=1000),
                            EnvSpec.of("InvertedPendulum-v5"))
        fresh.intake.store(ep)  # int64 columns, rows, D_E: OverflowError or anything else fails the test
        assert fresh.sampler.sample(P.SampleRequest(1, 8)).status == "ok"
        P.Episode.decode(ep.encode(), LIMITS)

    _fuzz(make_episode(3, ret=1.0, version=2).encode(), lambda b: P.Episode.decode(b, LIMITS), use)


def test_fuzzed_weights_are_usable_or_rejected():
    import time

    from silcr.actor.policy import NumpyPolicy, initial_weights

    def use(w):
        np.int64(w.version)  # stamped on episodes, stored as int64
        P.Stats({"latency_ms": 1000 * (time.time() - w.sent_at), "version": w.version}).encode()  # JSON, finite
        try:
            policy = NumpyPolicy(w, 4, 1)
        except (P.ProtocolError, ValueError):  # what the weights client counts and ignores
            return
        assert np.isfinite(policy.sample(np.zeros((2, 4), np.float32), np.random.default_rng(0))).all()

    _fuzz(initial_weights(4, 1, [8], 0).encode(), P.Weights.decode, use)


def test_fuzzed_sample_requests_are_served_or_refused(replay):
    def use(req):
        try:
            reply = replay.sampler.sample(req)
        except P.ProtocolError:
            return
        P.BatchReply.decode(reply.encode())

    _fuzz(P.SampleRequest(2, 8, 4, 50).encode(), P.SampleRequest.decode, use)


def test_fuzzed_batch_replies_are_trainable_or_rejected(replay):
    import torch

    from silcr.learner.update import to_tensor

    def use(reply):
        if reply.status != "ok":
            assert reply.retry_after_ms >= 0
            return
        header = reply.header
        n, size, online = header.batches, header.batch_size, header.online_rows
        online_versions, _ = header.by_table(reply.batch.policy_version)  # the learner's lag accounting
        assert online_versions.size and 1 <= online <= size
        for b in range(n):
            rows = reply.batch.rows(b, size).map(lambda a: to_tensor(a, torch.device("cpu")))
            assert rows.obs.shape[0] == rows.rewards.shape[0] == size and torch.isfinite(rows.rewards).all()
        if reply.disc is not None:
            m = reply.disc.expert_obs.shape[0] // n
            assert reply.disc.rows(n - 1, m).recent_actions.shape[0] == m

    _fuzz(replay.sampler.sample(P.SampleRequest(2, 8, 4, 50)).encode(), P.BatchReply.decode, use)


def test_fuzzed_control_messages_are_typed_or_rejected():
    _fuzz(P.ThrottleNotice(True).encode(), P.ThrottleNotice.decode, lambda t: isinstance(t.paused, bool) or pytest.fail())
    _fuzz(P.ShutdownNotice("finished").encode(), P.ShutdownNotice.decode,
          lambda s: isinstance(s.reason, str) or pytest.fail())


@pytest.mark.parametrize("payload, decode, reason", [  # ids: what each case is
    (_mutate(policy_version=2**63), lambda b: P.Episode.decode(b, LIMITS), "out_of_range"),
    (_mutate(seq=-1), lambda b: P.Episode.decode(b, LIMITS), "out_of_range"),
    (_pack({"v": 1, "kind": "weights", "version": 2**63, "arch": {}, "params": {}}), P.Weights.decode, "out_of_range"),
    (_pack({"v": 1, "kind": "weights", "version": 1, "arch": {}, "params": {}, "sent_at": float("nan")}),
     P.Weights.decode, "non_finite"),
    (_pack({"v": 1, "kind": "sample", "batches": 64, "batch_size": 65536}), P.SampleRequest.decode, "bad_request"),
    (_pack({"v": 1, "kind": "sample", "batches": 1, "batch_size": 8, "disc_batch_size": 8, "recent_window": 2**64 - 1}),
     P.SampleRequest.decode, "bad_request"),
    (_pack({"v": 1, "kind": "batch", "status": "not_ready", "meta": {"env_steps": 2**63}}), P.BatchReply.decode,
     "out_of_range"),
    (_pack({"v": 1, "kind": "batch", "status": "not_ready", "meta": {"expert_min_return": float("inf")}}),
     P.BatchReply.decode, "non_finite"),
    (_pack({"v": 1, "kind": "throttle", "paused": 2**63}), P.ThrottleNotice.decode, "bad_field"),
    (_pack({"v": 1, "kind": "shutdown", "reason": 7}), P.ShutdownNotice.decode, "bad_field"),
], ids=["episode-version-2^63", "episode-seq-negative", "weights-version-2^63", "weights-sent-at-nan",
        "sample-rows-over-bound", "sample-window-2^64", "reply-env-steps-2^63", "reply-return-inf",
        "throttle-not-bool", "shutdown-reason-not-str"])
def test_numbers_out_of_range_are_rejected_with_a_reason(payload, decode, reason):
    with pytest.raises(P.ProtocolError) as info:
        decode(payload)
    assert info.value.reason == reason
