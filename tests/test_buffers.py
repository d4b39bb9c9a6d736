"""D_O (OnlineFifo), D_E (ExpertHeap) and the mixed-batch rule."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from silcr.buffer_service.batches import compose_batches
from silcr.buffer_service.expert_heap import ExpertHeap
from silcr.buffer_service.labels import ConstantLabels, EnvLabels
from silcr.buffer_service.online_fifo import OnlineFifo
from silcr.common.protocol import Batch
from tests.conftest import make_episode


def _draw(table, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(seq, t) of `n` drawn transitions, for episodes made with `start=100 * seq`."""
    out = Batch.empty(n, 4, 1)
    table.gather(n, rng, out, slice(0, n), True)
    np.testing.assert_array_equal(out.next_obs, out.obs + 1)
    v = out.obs[:, 0].astype(np.int64)
    return v // 100, v % 100


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
    seqs, ts = _draw(fifo, 30_000, rng)
    assert set(seqs) == {2, 3, 4}
    assert ((ts >= 0) & (ts < 10)).all()
    # uniform over the 30 live transitions: each (episode, t) about 1/30
    counts = np.bincount((seqs - 2) * 10 + ts, minlength=30)
    assert counts.min() > 800 and counts.max() < 1200


def test_fifo_uniform_by_transition_not_by_episode():
    fifo = OnlineFifo(capacity=1000)
    fifo.add(make_episode(90, seq=0))
    fifo.add(make_episode(10, seq=1, start=100))
    seqs, _ = _draw(fifo, 20_000, np.random.default_rng(1))
    share_long = np.mean(seqs == 0)
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
    assert sorted([e.episode_return for e in heap.episodes()]) == [1.0, 3.0, 5.0]
    assert heap.offer(make_episode(10, ret=2.0, seq=5))  # better than the lowest: evicts it
    assert sorted([e.episode_return for e in heap.episodes()]) == [2.0, 3.0, 5.0]
    assert heap.evicted == 1 and heap.rejected == 2 and len(heap) == 30


def test_heap_evicts_lowest_until_total_fits():
    heap = ExpertHeap(capacity=30)
    for i, r in enumerate([1.0, 2.0, 9.0]):
        heap.offer(make_episode(10, ret=r, seq=i))
    assert heap.offer(make_episode(20, ret=5.0, seq=3))  # needs 20: evicts 1.0 and 2.0
    assert sorted([e.episode_return for e in heap.episodes()]) == [5.0, 9.0] and len(heap) == 30


def test_heap_rejection_never_loses_stored_episodes():
    heap = ExpertHeap(capacity=30)
    heap.offer(make_episode(10, ret=1.0, seq=0))
    heap.offer(make_episode(20, ret=9.0, seq=1))
    # Strictly better than 1.0, but evicting only worse episodes frees 10 of the 20 needed.
    assert not heap.offer(make_episode(20, ret=5.0, seq=2))
    assert sorted([e.episode_return for e in heap.episodes()]) == [1.0, 9.0] and len(heap) == 30 and heap.evicted == 0


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
    assert sorted([e.episode_return for e in heap.episodes()]) == pytest.approx(sorted(returns)[-10:], rel=1e-6)


def test_full_heap_gives_the_room_evictions_leave_only_to_better_episodes():
    def heap_after_a_gap(refill: str) -> ExpertHeap:
        heap = ExpertHeap(capacity=30, refill=refill)
        for i, r in enumerate([1.0, 2.0, 3.0]):
            assert heap.offer(make_episode(10, ret=r, seq=i))
        assert heap.offer(make_episode(5, ret=5.0, seq=3))  # no room: evicts the 10-step 1.0, leaving 5 free
        assert len(heap) == 25 and heap.min_return == 2.0 and heap.filled
        return heap

    heap = heap_after_a_gap("better")
    assert not heap.offer(make_episode(5, ret=0.5, seq=4))  # fits the gap, but the full D_E would refuse it
    assert not heap.offer(make_episode(5, ret=2.0, seq=5))  # a tie with the lowest neither
    assert heap.min_return == 2.0 and len(heap) == 25 and heap.rejected == 2
    assert heap.offer(make_episode(5, ret=2.5, seq=6))  # better than the lowest: takes the gap, evicting nothing
    assert len(heap) == 30 and heap.evicted == 1 and heap.min_return == 2.0

    heap = heap_after_a_gap("any")  # runs recorded before the option: anything that fits enters
    assert heap.offer(make_episode(5, ret=0.5, seq=4))
    assert heap.min_return == 0.5 and len(heap) == 30


def test_heap_before_it_first_fills_admits_whatever_fits():
    heap = ExpertHeap(capacity=30)
    for i, r in enumerate([5.0, 1.0, -3.0]):  # worse and worse, but there is room
        assert heap.offer(make_episode(10, ret=r, seq=i))
    assert not heap.filled and heap.min_return == -3.0


def _falls_after_filling(heap: ExpertHeap, offers) -> int:
    """How often D_E's lowest return fell from one offer of (length, return) to the next, once D_E had filled."""
    falls, lowest = 0, None
    for i, (n, ret) in enumerate(offers):
        heap.offer(make_episode(int(n), ret=float(ret), seq=i))
        if heap.filled:
            falls += lowest is not None and heap.min_return < lowest
            lowest = heap.min_return
    return falls


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 12), st.integers(-20, 20)), min_size=1, max_size=120))
def test_full_heap_lowest_return_never_falls(offers):
    """Once D_E has filled, its lowest return only rises (the official heap's property); with `refill="any"`
    it can fall (the next test)."""
    assert _falls_after_filling(ExpertHeap(capacity=30), offers) == 0


def test_the_lowest_return_falls_without_the_refill_rule():
    """The property above is not vacuous: on a random stream of variable-length episodes, `refill="any"` lets
    D_E's lowest return fall after D_E has filled, and `refill="better"` never does."""
    rng = np.random.default_rng(0)
    offers = list(zip(rng.integers(1, 13, 2000), rng.integers(-20, 21, 2000)))
    falls = {refill: _falls_after_filling(ExpertHeap(capacity=30, refill=refill), offers) for refill in ("better", "any")}
    assert falls["better"] == 0 and falls["any"] > 0, falls


def test_heap_state_keeps_whether_it_has_filled():
    heap = ExpertHeap(capacity=20)
    for i, r in enumerate([1.0, 2.0, 3.0]):
        heap.offer(make_episode(10, ret=r, seq=i))
    state = heap.state()
    again = ExpertHeap(capacity=20)
    again.restore(state)
    assert again.filled
    del state["filled"]  # a checkpoint written before the flag: an eviction shows D_E was full
    older = ExpertHeap(capacity=20)
    older.restore(state)
    assert older.filled


def test_heap_sampling_covers_stored_transitions():
    heap = ExpertHeap(capacity=30)
    for i, r in enumerate([1.0, 2.0, 3.0]):
        heap.offer(make_episode(10, ret=r, seq=i, start=100 * i))
    seqs, ts = _draw(heap, 6000, np.random.default_rng(0))
    assert set(seqs) == {0, 1, 2}
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
    out = compose_batches(fifo, heap, 3, 128, np.random.default_rng(0), ConstantLabels(), 4, 1)
    assert out.obs.shape == (384, 4) and out.actions.shape == (384, 1)
    for b in range(3):
        rows = slice(b * 128, (b + 1) * 128)
        r = out.rewards[rows]
        np.testing.assert_array_equal(r[:64], 0.0)
        np.testing.assert_array_equal(r[64:], 1.0)
        # The expert half comes from the 10 best episodes (returns 10..19, obs start 10000..19000).
        assert (out.obs[rows][64:, 0] >= 10_000).all()
    # next_obs is the following row of the same episode
    np.testing.assert_array_equal(out.next_obs[:, 0], out.obs[:, 0] + 1)


def test_batch_terminal_flags_only_on_last_step():
    fifo, heap = _filled()
    out = compose_batches(fifo, heap, 20, 128, np.random.default_rng(1), ConstantLabels(), 4, 1)
    t = out.obs[:, 0] % 1000  # time step within its episode
    seq = out.obs[:, 0] // 1000
    last = t == 9
    np.testing.assert_array_equal(out.terminated.astype(bool), last & (seq % 2 == 0))
    np.testing.assert_array_equal(out.truncated.astype(bool), last & (seq % 2 == 1))
    assert out.terminated.any() and out.truncated.any()


def test_batch_flags_when_gymnasium_reports_both_and_policy_versions():
    fifo = OnlineFifo(1000)
    fifo.add(make_episode(3, ret=1.0, seq=0, start=0, terminated=True, truncated=True))
    out = compose_batches(fifo, None, 1, 64, np.random.default_rng(0), EnvLabels(), 4, 1)
    last = out.obs[:, 0] == 2
    assert last.any() and not last.all()
    np.testing.assert_array_equal(out.terminated.astype(bool), last)  # termination wins
    assert not out.truncated.any()
    np.testing.assert_array_equal(out.policy_version, fifo.episodes()[0].policy_version)


def test_sac_batches_use_env_rewards_from_online_only():
    fifo = OnlineFifo(1000)
    for i in range(5):
        fifo.add(make_episode(10, ret=float(i + 1), seq=i, start=1000 * i))
    out = compose_batches(fifo, None, 2, 64, np.random.default_rng(0), EnvLabels(), 4, 1)
    t = out.obs[:, 0] % 1000
    seq = out.obs[:, 0] // 1000
    expected = np.where(t == 9, seq + 1, 0.0)
    np.testing.assert_array_equal(out.rewards, expected)


# --- the service state: duplicates --------------------------------------------------


def test_an_episode_is_never_stored_twice_but_a_restarted_actor_is_welcome():
    from silcr.buffer_service.replay import ReplayState
    from silcr.common import protocol as P
    from silcr.common.config import Config
    from silcr.common.envs import EnvSpec

    state = ReplayState(Config(run="t", env="InvertedPendulum-v5"), EnvSpec.of("InvertedPendulum-v5"))
    first = make_episode(5, ret=1.0, seq=0)
    first.incarnation = 7
    state.intake.ingest(first.encode())
    with pytest.raises(P.ProtocolError) as info:
        state.intake.ingest(first.encode())
    assert info.value.reason == "duplicate"
    restarted = make_episode(5, ret=1.0, seq=0)
    restarted.incarnation = 8
    state.intake.ingest(restarted.encode())
    assert state.intake.episodes_received == 2 and len(state.fifo) == 10
    # An episode sent again is not a rejection (an actor resends what it has no ack for): counted on its own.
    assert state.intake.rejections == {} and state.stats()["episodes_duplicate"] == 1
    assert state.intake.episodes_missing == 0


def test_an_actor_that_holds_its_episodes_gets_them_stored_in_order_and_none_counted_missing():
    """Issue 63: an episode after a gap is refused and its sender asked again from the gap (it still holds
    them, `resend_from`); only what a sender no longer holds is missing."""
    from silcr.buffer_service.replay import ReplayState
    from silcr.common import protocol as P
    from silcr.common.config import Config
    from silcr.common.envs import EnvSpec

    state = ReplayState(Config(run="t", env="InvertedPendulum-v5"), EnvSpec.of("InvertedPendulum-v5"))

    def send(seq, held_from):
        ep = make_episode(3, ret=float(seq), seq=seq)
        ep.incarnation, ep.resend_from = 9, held_from
        state.intake.store(P.Episode.decode(ep.encode(), state.limits))

    send(0, 0)
    send(1, 1)
    with pytest.raises(P.ProtocolError) as info:
        send(4, 2)  # 2 and 3 were lost on the way; the actor still holds them
    assert info.value.reason == "out_of_order" and "asked for 2" in str(info.value)
    probe = make_episode(3, seq=4)
    probe.incarnation, probe.resend_from = 9, 2
    assert state.intake.expected(probe) == 2 and state.intake.last_seq[(0, 9)] == 1
    for seq in (2, 3, 4):
        send(seq, 2)
    send(7, 7)  # the actor gave up 5 and 6 (it stopped with them unconfirmed, say): missing for good
    assert [e.seq for e in state.fifo.episodes()] == [0, 1, 2, 3, 4, 7]
    assert state.intake.episodes_missing == 2
    assert state.stats()["episodes_out_of_order"] == 1 and state.intake.rejections == {}
    with pytest.raises(P.ProtocolError, match="after the episode's own seq"):
        bad = make_episode(3, seq=8)
        bad.resend_from = 9
        P.Episode.decode(bad.encode(), state.limits)


def test_gaps_in_an_actors_sequence_numbers_are_counted_as_missing_episodes():
    from silcr.buffer_service.replay import ReplayState
    from silcr.common.config import Config
    from silcr.common.envs import EnvSpec

    cfg = Config(run="t", env="InvertedPendulum-v5")
    state = ReplayState(cfg, EnvSpec.of("InvertedPendulum-v5"))
    for incarnation, seqs in ((1, [0, 1, 3, 6]), (2, [4, 5])):  # a sender first seen at 4: no gap known before it
        for seq in seqs:
            ep = make_episode(5, ret=1.0, seq=seq)
            ep.incarnation = incarnation
            state.intake.ingest(ep.encode())
    assert state.intake.episodes_missing == 1 + 2 and state.stats()["episodes_missing"] == 3
    again = ReplayState(cfg, EnvSpec.of("InvertedPendulum-v5"))
    again.restore(state.state())
    assert again.intake.episodes_missing == 3  # kept across a restart


# --- contiguous storage: ring reuse, compaction, copies for holders ------------------


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 30), min_size=1, max_size=80), st.integers(30, 120))
def test_fifo_ring_keeps_the_newest_episodes_intact(lengths, capacity):
    fifo = OnlineFifo(capacity=capacity, max_episode_steps=30)
    added = []
    for i, n in enumerate(lengths):
        ep = make_episode(n, seq=i, start=100 * i)
        added.append(ep)
        fifo.add(ep)
        stored = fifo.episodes()
        # a suffix of what arrived, within capacity, each episode's rows intact
        assert [e.seq for e in stored] == list(range(i + 1 - len(stored), i + 1))
        assert len(fifo) == sum(e.length for e in stored) <= capacity
        if fifo.evicted_for_rows == 0:  # then exactly the capacity rule decided
            assert len(stored) == len(added) or len(fifo) + added[-len(stored) - 1].length > capacity
    for e in added:  # stored or evicted (and copied out before its rows were reused)
        np.testing.assert_array_equal(e.obs[:, 0], 100 * e.seq + np.arange(e.length + 1))
    seqs, ts = _draw(fifo, 2000, np.random.default_rng(0))
    live = {e.seq: e.length for e in fifo.episodes()}
    assert set(seqs) <= set(live) and all(t < live[s] for s, t in zip(seqs, ts))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 12), st.integers(-5, 5)), min_size=1, max_size=80))
def test_heap_rows_survive_eviction_compaction_and_growth(offers):
    heap = ExpertHeap(capacity=30)
    held = []
    for i, (n, ret) in enumerate(offers):
        if heap.offer(make_episode(n, ret=float(ret), seq=i, start=100 * i)):
            held.append(heap.state()["entries"])
    for entries in held:  # every episode ever stored, evicted ones included, kept its data
        for e, _, _ in entries:
            np.testing.assert_array_equal(e.obs[:, 0], 100 * e.seq + np.arange(e.length + 1))
    assert len(heap) == sum(e.length for e in heap.episodes()) <= 30
    seqs, ts = _draw(heap, 2000, np.random.default_rng(0))
    live = {e.seq: e.length for e in heap.episodes()}
    assert set(seqs) == set(live) and all(t < live[s] for s, t in zip(seqs, ts))


def test_fifo_with_short_episodes_runs_out_of_rows_before_transitions_and_counts_it():
    fifo = OnlineFifo(capacity=64, max_episode_steps=1)
    for i in range(200):
        fifo.add(make_episode(1, seq=i, start=100 * i))
    # 1-step episodes need 2 rows each: 64 + 2 + 4 rows hold 35 of them, not 64
    assert fifo.evicted_for_rows > 0 and len(fifo) < 64
    assert fifo.evicted_episodes == 200 - fifo.num_episodes
