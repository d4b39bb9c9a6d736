"""IRCR (`--algo ircr`): each row labelled with its episode's credit, min-max normalised over D_O and D_E.

The labels are checked against a hand computation, through the buffer's own state, as
episodes enter and leave both tables and move the minimum and the maximum. Learning is
checked in test_learning.py (the learning test's task) and test_ranking.py (the task
where only the ranking helps).
"""

from __future__ import annotations

import numpy as np
import pytest

from silcr.buffer_service.labels import CreditLabels
from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from tests.conftest import make_episode

ENV = "InvertedPendulum-v5"  # 4-d observations, 1-d actions, as make_episode's


def _replay(online: int, expert: int) -> ReplayState:
    cfg = Config(run="ircr", env=ENV, algo="ircr", online_capacity=online, expert_capacity=expert, learning_starts=0,
                 batch_size=64)
    return ReplayState(cfg, EnvSpec.of(ENV))


def _labels_by_episode(replay: ReplayState, batches: int = 8) -> dict[int, set[float]]:
    """The labels a batch gave each episode, by seq (make_episode's start = 1000 * seq)."""
    reply = replay.sampler.sample(P.SampleRequest(batches, 64))
    assert reply.status == "ok"
    seq = (reply.batch.obs[:, 0] // 1000).astype(int)
    out: dict[int, set[float]] = {}
    for s, r in zip(seq, reply.batch.rewards):
        out.setdefault(int(s), set()).add(float(r))
    return out


def _expected(credits: dict[int, float], live: set[int]) -> dict[int, float]:
    lo, hi = min(credits[s] for s in live), max(credits[s] for s in live)
    return {s: (credits[s] - lo) / (hi - lo) for s in live}


def test_the_credit_range_follows_episodes_in_and_out():
    labels = CreditLabels()
    eps = [make_episode(n, ret=r, seq=i) for i, (n, r) in enumerate([(10, 5.0), (4, 8.0), (5, -5.0), (10, 5.0)])]
    assert labels.credit_range() is None
    for ep in eps:
        labels.entered(ep)
    assert labels.credit_range() == (-1.0, 2.0)  # -5/5 and 8/4
    labels.left(eps[2])
    assert labels.credit_range() == (0.5, 2.0)
    labels.left(eps[1])
    assert labels.credit_range() == (0.5, 0.5)  # two episodes share the credit 0.5
    labels.left(eps[0])
    assert labels.credit_range() == (0.5, 0.5)  # one of them is still there
    labels.entered(eps[2])
    assert labels.credit_range() == (-1.0, 0.5)


def test_many_episodes_passing_through_keep_the_heaps_small():
    labels = CreditLabels()
    rng = np.random.default_rng(0)
    live = []
    for i in range(5000):
        ep = make_episode(int(rng.integers(1, 20)), ret=float(rng.normal()), seq=i)
        labels.entered(ep)
        live.append(ep)
        if len(live) > 50:
            labels.left(live.pop(0))
    credits = [e.episode_return / e.length for e in live]
    assert labels.credit_range() == (min(credits), max(credits))
    assert len(labels._low) <= 2 * 51 + 64 + 1


def test_rows_carry_their_episodes_normalised_credit_as_d_o_and_d_e_turn_over():
    # D_O holds 40 transitions (4 episodes of 10), D_E 20 (the best 2 by return).
    replay = _replay(online=40, expert=20)
    credits: dict[int, float] = {}

    def add(seq: int, ret: float) -> None:
        replay.intake.store(make_episode(10, ret=ret, seq=seq, start=1000 * seq))
        credits[seq] = ret / 10

    for seq, ret in enumerate([1.0, 2.0, 3.0, 4.0]):
        add(seq, ret)
    # D_O: 0-3; D_E: 2, 3. Credits 0.1 .. 0.4.
    got = _labels_by_episode(replay)
    want = _expected(credits, {0, 1, 2, 3})
    assert set(got) == {0, 1, 2, 3}
    assert got[0] == {0.0} and got[3] == {1.0}
    for seq, values in got.items():
        assert len(values) == 1 and values.pop() == pytest.approx(want[seq], abs=1e-6), seq

    add(4, -6.0)  # D_O evicts episode 0; the new minimum is episode 4's credit, -0.6
    got = _labels_by_episode(replay)
    want = _expected(credits, {1, 2, 3, 4})
    assert 0 not in got and got[4] == {0.0} and got[3] == {1.0}
    for seq, values in got.items():
        assert len(values) == 1 and values.pop() == pytest.approx(want[seq], abs=1e-6), seq

    add(5, 0.0)  # D_O evicts episode 1
    add(6, 0.5)  # D_O evicts episode 2; D_E still holds episodes 2 and 3 (the best returns)
    add(7, 0.2)  # D_O evicts episode 3: D_O now holds 4-7, D_E 2 and 3
    got = _labels_by_episode(replay, batches=16)
    want = _expected(credits, {2, 3, 4, 5, 6, 7})  # the maximum, 0.4, is episode 3's, in D_E only
    assert set(got) == {2, 3, 4, 5, 6, 7}
    for seq, values in got.items():
        assert len(values) == 1 and values.pop() == pytest.approx(want[seq], abs=1e-6), seq

    add(8, 9.0)  # D_O evicts episode 4 (the minimum), D_E evicts episode 2; new maximum 0.9
    add(9, 7.0)  # D_O evicts 5; D_E evicts 3: D_E holds 8 and 9
    got = _labels_by_episode(replay, batches=16)
    live = {6, 7, 8, 9}
    want = _expected(credits, live)
    assert set(got) == live and got[8] == {1.0} and got[7] == {0.0}
    for seq, values in got.items():
        assert len(values) == 1 and values.pop() == pytest.approx(want[seq], abs=1e-6), seq


def test_half_of_each_batch_comes_from_d_e():
    replay = _replay(online=1000, expert=30)
    for seq in range(10):
        replay.intake.store(make_episode(10, ret=float(seq), seq=seq, start=1000 * seq))
    reply = replay.sampler.sample(P.SampleRequest(4, 64))
    assert reply.meta["online_rows"] == 32
    seq = (reply.batch.obs[:, 0] // 1000).reshape(4, 64)
    assert set(np.unique(seq[:, 32:])) <= {7, 8, 9}  # the top 3 by return


def test_equal_credits_label_every_row_zero():
    """On the episodic InvertedPendulum every step earns 1, so every episode's credit is 1:
    the normalisation has no range and IRCR's reward carries no signal there (docs/algorithm.md)."""
    replay = _replay(online=1000, expert=100)
    for seq, n in enumerate([5, 9, 30, 12]):
        replay.intake.store(make_episode(n, ret=float(n), seq=seq, start=1000 * seq))
    reply = replay.sampler.sample(P.SampleRequest(2, 64))
    assert (reply.batch.rewards == 0.0).all()


def test_a_checkpoint_restores_the_credit_range(tmp_path):
    from silcr.buffer_service import snapshot

    replay = _replay(online=40, expert=20)
    for seq, ret in enumerate([1.0, -6.0, 3.0, 9.0, 0.5]):
        replay.intake.store(make_episode(10, ret=ret, seq=seq, start=1000 * seq))
    path = tmp_path / "buffer.ckpt"
    snapshot.write(path, snapshot.take(replay))
    back = _replay(online=40, expert=20)
    snapshot.restore(path, back)
    assert back.labeller.credit_range() == replay.labeller.credit_range() == (-0.6, 0.9)
