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
    back = P.BatchReply.decode(P.BatchReply("ok", {"env_steps": 5}, batch).encode())
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
