"""D_O (OnlineFifo), D_E (ExpertHeap) and the mixed-batch rule."""

from __future__ import annotations

import numpy as np
import pytest

from buffer_service.batches import compose_batches
from buffer_service.expert_heap import ExpertHeap
from buffer_service.online_fifo import OnlineFifo
from tests.conftest import make_episode


# --- OnlineFifo ---------------------------------------------------------------


def test_fifo_wraps_around_by_evicting_oldest_whole_episodes():
    fifo = OnlineFifo(capacity=25)
    for i in range(10):
        fifo.add(make_episode(10, seq=i, start=100 * i))
    # 25 transitions of room: only the two newest whole episodes fit after the third arrives.
    assert len(fifo) == 20 and fifo.num_episodes == 2
    assert [e.seq for e in fifo.episodes()] == [8, 9]
    assert fifo.evicted_episodes == 8


def test_fifo_samples_only_live_transitions_uniformly():
    fifo = OnlineFifo(capacity=30)
    for i in range(5):
        fifo.add(make_episode(10, seq=i, start=100 * i))
    rng = np.random.default_rng(0)
    eps, ts = fifo.sample_locations(30_000, rng)
    seqs = np.array([e.seq for e in eps])
    assert set(seqs) == {2, 3, 4}
    assert ((ts >= 0) & (ts < 10)).all()
    # uniform over the 30 live transitions: each (episode, t) about 1/30
    counts = np.bincount((seqs - 2) * 10 + ts, minlength=30)
    assert counts.min() > 800 and counts.max() < 1200


def test_fifo_uniform_by_transition_not_by_episode():
    fifo = OnlineFifo(capacity=1000)
    fifo.add(make_episode(90, seq=0))
    fifo.add(make_episode(10, seq=1))
    eps, _ = fifo.sample_locations(20_000, np.random.default_rng(1))
    share_long = np.mean([e.seq == 0 for e in eps])
    assert 0.88 < share_long < 0.92


def test_fifo_rejects_episode_larger_than_capacity():
    with pytest.raises(ValueError):
        OnlineFifo(5).add(make_episode(6))


# --- ExpertHeap -----------------------------------------------------------------


def test_heap_admits_while_room_then_only_strictly_better():
    heap = ExpertHeap(capacity=30)
    for i, r in enumerate([5.0, 1.0, 3.0]):
        assert heap.offer(make_episode(10, ret=r, seq=i))
    assert len(heap) == 30 and heap.min_return == 1.0
    assert not heap.offer(make_episode(10, ret=1.0, seq=3))  # tie with the lowest: rejected
    assert not heap.offer(make_episode(10, ret=0.5, seq=4))  # worse: rejected
    assert sorted(heap.returns()) == [1.0, 3.0, 5.0]
    assert heap.offer(make_episode(10, ret=2.0, seq=5))  # better than the lowest: evicts it
    assert sorted(heap.returns()) == [2.0, 3.0, 5.0]
    assert heap.evicted == 1 and heap.rejected == 2 and len(heap) == 30


def test_heap_evicts_lowest_until_total_fits():
    heap = ExpertHeap(capacity=30)
    for i, r in enumerate([1.0, 2.0, 9.0]):
        heap.offer(make_episode(10, ret=r, seq=i))
    assert heap.offer(make_episode(20, ret=5.0, seq=3))  # needs 20: evicts 1.0 and 2.0
    assert sorted(heap.returns()) == [5.0, 9.0] and len(heap) == 30


def test_heap_rejection_never_loses_stored_episodes():
    heap = ExpertHeap(capacity=30)
    heap.offer(make_episode(10, ret=1.0, seq=0))
    heap.offer(make_episode(20, ret=9.0, seq=1))
    # Strictly better than 1.0, but evicting only worse episodes frees 10 of the 20 needed.
    assert not heap.offer(make_episode(20, ret=5.0, seq=2))
    assert sorted(heap.returns()) == [1.0, 9.0] and len(heap) == 30 and heap.evicted == 0


def test_heap_ties_evict_older_first():
    heap = ExpertHeap(capacity=20)
    heap.offer(make_episode(10, ret=1.0, seq=0))
    heap.offer(make_episode(10, ret=1.0, seq=1))
    assert heap.offer(make_episode(10, ret=2.0, seq=2))
    assert sorted(e.seq for e in heap.episodes()) == [1, 2]


def test_heap_rejects_episode_longer_than_capacity():
    heap = ExpertHeap(capacity=5)
    assert not heap.offer(make_episode(6, ret=100.0))
    assert len(heap) == 0 and heap.rejected == 1


def test_heap_keeps_top_m_under_random_stream():
    rng = np.random.default_rng(3)
    heap = ExpertHeap(capacity=100)
    returns = rng.normal(size=500)
    for i, r in enumerate(returns):
        heap.offer(make_episode(10, ret=float(r), seq=i))
    assert sorted(heap.returns()) == pytest.approx(sorted(returns)[-10:], rel=1e-6)


def test_heap_sampling_covers_stored_transitions():
    heap = ExpertHeap(capacity=30)
    for i, r in enumerate([1.0, 2.0, 3.0]):
        heap.offer(make_episode(10, ret=r, seq=i, start=100 * i))
    eps, ts = heap.sample_locations(6000, np.random.default_rng(0))
    assert {e.seq for e in eps} == {0, 1, 2}
    assert ((ts >= 0) & (ts < 10)).all()


# --- mixed batches --------------------------------------------------------------


def _filled(constant: bool = True):
    fifo, heap = OnlineFifo(1000), ExpertHeap(100)
    for i in range(20):
        ep = make_episode(10, ret=float(i), seq=i, start=1000 * i, terminated=i % 2 == 0, truncated=i % 2 == 1)
        fifo.add(ep)
        heap.offer(ep)
    return fifo, heap


def test_silcr_batches_are_half_online_reward0_half_expert_reward1():
    fifo, heap = _filled()
    out = compose_batches(fifo, heap, 3, 128, np.random.default_rng(0), True, 4, 1)
    assert out["obs"].shape == (384, 4) and out["actions"].shape == (384, 1)
    for b in range(3):
        rows = slice(b * 128, (b + 1) * 128)
        r = out["rewards"][rows]
        np.testing.assert_array_equal(r[:64], 0.0)
        np.testing.assert_array_equal(r[64:], 1.0)
        # The expert half comes from the 10 best episodes (returns 10..19, obs start 10000..19000).
        assert (out["obs"][rows][64:, 0] >= 10_000).all()
    # next_obs is the following row of the same episode
    np.testing.assert_array_equal(out["next_obs"][:, 0], out["obs"][:, 0] + 1)


def test_batch_terminal_flags_only_on_last_step():
    fifo, heap = _filled()
    out = compose_batches(fifo, heap, 20, 128, np.random.default_rng(1), True, 4, 1)
    t = out["obs"][:, 0] % 1000  # time step within its episode
    seq = out["obs"][:, 0] // 1000
    last = t == 9
    np.testing.assert_array_equal(out["terminated"].astype(bool), last & (seq % 2 == 0))
    np.testing.assert_array_equal(out["truncated"].astype(bool), last & (seq % 2 == 1))
    assert out["terminated"].any() and out["truncated"].any()


def test_batch_flags_when_gymnasium_reports_both_and_policy_versions():
    fifo = OnlineFifo(1000)
    fifo.add(make_episode(3, ret=1.0, seq=0, start=0, terminated=True, truncated=True))
    out = compose_batches(fifo, None, 1, 64, np.random.default_rng(0), False, 4, 1)
    last = out["obs"][:, 0] == 2
    assert last.any() and not last.all()
    np.testing.assert_array_equal(out["terminated"].astype(bool), last)  # termination wins
    assert not out["truncated"].any()
    np.testing.assert_array_equal(out["policy_version"], fifo.episodes()[0].policy_version)


def test_sac_batches_use_env_rewards_from_online_only():
    fifo = OnlineFifo(1000)
    for i in range(5):
        fifo.add(make_episode(10, ret=float(i + 1), seq=i, start=1000 * i))
    out = compose_batches(fifo, None, 2, 64, np.random.default_rng(0), False, 4, 1)
    t = out["obs"][:, 0] % 1000
    seq = out["obs"][:, 0] // 1000
    expected = np.where(t == 9, seq + 1, 0.0)
    np.testing.assert_array_equal(out["rewards"], expected)


# --- the service state: duplicates --------------------------------------------------


def test_an_episode_is_never_stored_twice_but_a_restarted_actor_is_welcome():
    from buffer_service.service import ReplayState
    from common import protocol as P
    from common.config import Config
    from common.envs import EnvSpec

    state = ReplayState(Config(run="t", env="InvertedPendulum-v5"), EnvSpec.of("InvertedPendulum-v5"))
    first = make_episode(5, ret=1.0, seq=0)
    first.incarnation = 7
    state.ingest(P.EpisodeCodec.encode(first))
    with pytest.raises(P.ProtocolError) as info:
        state.ingest(P.EpisodeCodec.encode(first))
    assert info.value.reason == "duplicate"
    restarted = make_episode(5, ret=1.0, seq=0)
    restarted.incarnation = 8
    state.ingest(P.EpisodeCodec.encode(restarted))
    assert state.episodes_received == 2 and len(state.fifo) == 10
    assert state.rejections == {"duplicate": 1}
