"""Buffer checkpoints: D_O, D_E and counters survive a restart; a corrupt file is refused."""

from __future__ import annotations

import numpy as np
import pytest

from silcr.buffer_service import snapshot
from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from tests.conftest import make_episode

ENV = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def spec():
    return EnvSpec.of(ENV)


def _state(spec, **kw):
    return ReplayState(Config(run="snap", env=ENV, expert_capacity=60, online_capacity=200, learning_starts=10, **kw), spec)


def _fill(state, n=30, first_seq=0):
    rng = np.random.default_rng(first_seq)
    for i in range(first_seq, first_seq + n):
        state.intake.ingest(make_episode(int(rng.integers(5, 15)), ret=float(rng.normal()), seq=i, start=i * 100).encode())
    state.sampler.answer(P.SampleRequest(2, 16).encode())


def test_snapshot_restores_both_tables_and_counters(tmp_path, spec):
    state = _state(spec)
    _fill(state)
    path = tmp_path / "buffer.ckpt"
    snap = snapshot.take(state)
    # Episodes in both tables are written once.
    held = {(e.actor_id, e.seq) for e in state.fifo.episodes() + state.heap.episodes()}
    assert len(snap.episodes) == len(held) < state.fifo.num_episodes + state.heap.num_episodes
    snapshot.write(path, snap)

    back = _state(spec)
    snapshot.restore(path, back)
    assert [e.seq for e in back.fifo.episodes()] == [e.seq for e in state.fifo.episodes()]
    assert sorted([e.episode_return for e in back.heap.episodes()]) == sorted([e.episode_return for e in state.heap.episodes()])
    assert len(back.heap) == len(state.heap) and len(back.fifo) == len(state.fifo)
    for part, name in (("intake", "episodes_received"), ("intake", "transitions_received"),
                       ("sampler", "batches_served"), ("intake", "last_seq")):
        assert getattr(getattr(back, part), name) == getattr(getattr(state, part), name)
    assert (back.limiter.inserts, back.limiter.samples) == (state.limiter.inserts, state.limiter.samples)
    # The restored tables hold the same data, row for row.
    for a, b in zip(state.fifo.episodes(), back.fifo.episodes()):
        np.testing.assert_array_equal(a.obs, b.obs)
        np.testing.assert_array_equal(a.actions, b.actions)
    entries = [sorted(s.heap.state()["entries"], key=lambda e: e[2]) for s in (state, back)]  # by admission order
    for a, b in zip(*entries):
        np.testing.assert_array_equal(a[0].obs, b[0].obs)
    # The same eviction order: the next better episode evicts the same one in both.
    ep = make_episode(10, ret=5.0, seq=99, start=1e4).encode()
    state.intake.ingest(ep)
    back.intake.ingest(ep)
    assert sorted([e.episode_return for e in back.heap.episodes()]) == sorted([e.episode_return for e in state.heap.episodes()])
    # An episode sent before the checkpoint is still recognised as a duplicate.
    with pytest.raises(P.ProtocolError, match="again"):
        back.intake.ingest(make_episode(5, seq=3).encode())


def test_corrupt_or_foreign_snapshot_is_refused(tmp_path, spec):
    state = _state(spec)
    _fill(state)
    path = tmp_path / "buffer.ckpt"
    snapshot.write(path, snapshot.take(state))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(snapshot.SnapshotError, match="truncated|corrupt"):
        snapshot.restore(path, _state(spec))
    path.write_bytes(b"\x00garbage")
    with pytest.raises(snapshot.SnapshotError, match="not a silcr buffer checkpoint|corrupt"):
        snapshot.restore(path, _state(spec))
    snapshot.write(path, snapshot.take(state))
    with pytest.raises(snapshot.SnapshotError, match="this run is sac"):
        snapshot.restore(path, _state(spec, algo="sac"))


def test_a_failed_write_leaves_the_previous_checkpoint(tmp_path, spec, monkeypatch):
    state = _state(spec)
    _fill(state, 10)
    path = tmp_path / "buffer.ckpt"
    snapshot.write(path, snapshot.take(state))
    before = path.read_bytes()
    _fill(state, 5, first_seq=10)

    def crash(ep):
        raise OSError("disk full")

    monkeypatch.setattr(P.Episode, "encode", crash)
    with pytest.raises(OSError):
        snapshot.write(path, snapshot.take(state))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["buffer.ckpt"]


def test_snapshot_taken_then_overwritten_still_writes_what_was_taken(tmp_path, spec):
    """The tables reuse their rows after a snapshot is taken; the file must hold the rows as they were."""
    state = _state(spec)
    _fill(state)
    snap = snapshot.take(state)
    taken = {(e.seq, bytes(e.obs.tobytes())) for e in snap.episodes}
    # enough better episodes to evict every D_O and D_E episode (ring reuse, D_E compaction)
    for i in range(100, 200):
        state.intake.ingest(make_episode(10, ret=10.0 + i, seq=i, start=i * 100).encode())
    assert not {e.seq for e in state.fifo.episodes() + state.heap.episodes()} & {s for s, _ in taken}
    path = tmp_path / "buffer.ckpt"
    snapshot.write(path, snap)
    back = _state(spec)
    restored = snapshot.restore(path, back)
    assert {(e.seq, bytes(e.obs.tobytes())) for e in restored.episodes} == taken


def test_every_counter_the_stats_publish_survives_a_restore(tmp_path, spec):
    from silcr.common.inbox import Inbox

    state = _state(spec)
    _fill(state, 60)  # D_O (200 transitions) evicts; D_E (60) admits, evicts and rejects
    with pytest.raises(P.ProtocolError):
        state.intake.ingest(b"not an episode")
    with pytest.raises(P.ProtocolError):
        state.sampler.answer(b"not a request")
    while state.sampler.sample(P.SampleRequest(64, 8), keep_ratio=True).status == "ok":  # until the ratio says wait
        pass
    inbox, writer = Inbox(), snapshot.BackgroundWriter(tmp_path / "buffer.ckpt")
    inbox.restore({"blocked_puts": 3, "dropped_at_close": 2})
    writer.restore({"written": 4, "skipped": 1, "failed": 1})
    before = state.stats() | inbox.state() | writer.state()
    counters = ["online_evicted", "expert_admitted", "expert_rejected", "expert_evicted", "episodes_received",
                "transitions_received", "episodes_rejected", "batches_served", "sample_requests",
                "sample_requests_rejected", "not_ready_replies", "blocked_puts", "dropped_at_close", "written", "skipped", "failed"]
    assert all(before[k] > 0 for k in counters), {k: before[k] for k in counters}  # every one of them was counted

    snapshot.write(writer.path, snapshot.take(state, inbox=inbox, writer=writer))
    back, inbox2, writer2 = _state(spec), Inbox(), snapshot.BackgroundWriter(writer.path)
    snap = snapshot.restore(writer.path, back)
    inbox2.restore(snap.parts["inbox"])
    writer2.restore(snap.parts["writer"])
    after = back.stats() | inbox2.state() | writer2.state()
    for key, value in before.items():
        if key not in ("time", "uptime_s"):
            assert after[key] == value, key


def test_a_version_1_checkpoint_still_loads(tmp_path, spec):
    """silcr 0.1 wrote the tables' fields one by one; a buffer upgraded mid-run keeps what it had."""
    import msgpack

    state = _state(spec)
    _fill(state)
    episodes, index = [], {}

    def ref(ep):
        key = (ep.actor_id, ep.incarnation, ep.seq)
        if key not in index:
            index[key] = len(episodes)
            episodes.append(ep)
        return index[key]

    header = {"v": 1, "kind": "silcr-buffer", "env": ENV, "algo": "silcr", "written_at": 0.0,
              "counters": {"episodes_received": state.intake.episodes_received,
                           "transitions_received": state.transitions_received,
                           "batches_served": state.sampler.batches_served, "sample_requests": state.sampler.sample_requests,
                           "last_episode_version": state.intake.last_episode_version, "rejections": {},
                           "fifo_evicted": state.fifo.evicted_episodes,
                           "heap": [state.heap.admitted, state.heap.rejected, state.heap.evicted]},
              "limiter": {"inserts": state.limiter.inserts, "samples": state.limiter.samples},
              "last_seq": [[a, inc, seq] for (a, inc), seq in state.intake.last_seq.items()],
              "fifo": [ref(e) for e in state.fifo.episodes()],
              "heap": [[ref(e), ret, order] for e, ret, order in state.heap.state()["entries"]]}
    header["n_episodes"] = len(episodes)
    path = tmp_path / "v1.ckpt"
    path.write_bytes(msgpack.packb(header) + b"".join(msgpack.packb(e.encode()) for e in episodes))
    back = _state(spec)
    snapshot.restore(path, back)
    assert [e.seq for e in back.fifo.episodes()] == [e.seq for e in state.fifo.episodes()]
    assert sorted([e.episode_return for e in back.heap.episodes()]) == sorted([e.episode_return for e in state.heap.episodes()])
    assert back.transitions_received == state.transitions_received and back.limiter.samples == state.limiter.samples


def test_a_version_2_checkpoint_loads_into_the_parts(tmp_path, spec):
    """silcr 0.5 (before the buffer's state was split into parts) kept the intake's and the sampler's counters
    in one map. tests/golden/buffer-v2.ckpt was written by that code (commit 79d53fd), with every stats field
    it published beside it in buffer-v2.json: all of them come back, and the restored buffer goes on."""
    import json

    from tests.helpers import REPO

    golden = REPO / "tests" / "golden"
    expected = json.loads((golden / "buffer-v2.json").read_text())
    back = _state(spec)
    snap = snapshot.restore(golden / "buffer-v2.ckpt", back)
    assert snap.header["v"] == 2
    stats = back.stats()
    for key, value in expected.items():
        if key in stats and key not in ("run",):
            assert stats[key] == value, key
    assert [e.seq for e in back.fifo.episodes()] == expected["fifo_seqs"]
    assert sorted(e.episode_return for e in back.heap.episodes()) == expected["heap_returns"]
    assert back.limiter.state() == expected["limiter"]
    assert [[a, inc, s] for (a, inc), s in back.intake.last_seq.items()] == expected["last_seq"]
    with pytest.raises(P.ProtocolError, match="again"):  # the senders' sequence numbers came back too
        back.intake.ingest(make_episode(5, ret=0.0, seq=expected["last_seq"][0][2], start=0).encode())
    # written again, it is today's version, by part
    snapshot.write(tmp_path / "v3.ckpt", snapshot.take(back))
    again = _state(spec)
    assert snapshot.restore(tmp_path / "v3.ckpt", again).header["v"] == snapshot.SNAPSHOT_VERSION == 3
    assert set(snapshot.take(again).header["state"]) == {"tables", "intake", "sampler", "limiter"}
    assert {k: v for k, v in again.stats().items() if k not in ("time", "uptime_s")} == \
        {k: v for k, v in back.stats().items() if k not in ("time", "uptime_s")}


def test_the_rollout_return_is_the_mean_of_the_last_100_episodes_and_survives_a_restart(tmp_path, spec):
    """`rollout_return` / `rollout_length` (progress.csv, stats, every reply's meta): the actors' own last 100
    episodes, not all of them and not D_E's; a restart from a checkpoint goes on with the same window."""
    state = _state(spec)
    assert state.sampler.describe()["rollout_return"] is None and state.stats()["rollout_length"] is None
    for i in range(150):
        state.intake.ingest(make_episode(5 + i % 3, ret=float(i), seq=i, start=i * 100).encode())
    last = range(50, 150)
    meta = state.sampler.describe()
    assert meta["rollout_return"] == pytest.approx(sum(last) / 100)
    assert meta["rollout_length"] == pytest.approx(sum(5 + i % 3 for i in last) / 100)
    reply = P.BatchReply.decode(state.sampler.answer(P.SampleRequest(1, 16).encode()).encode())
    assert reply.meta["rollout_return"] == meta["rollout_return"]
    snapshot.write(tmp_path / "buffer.ckpt", snapshot.take(state))
    back = _state(spec)
    snapshot.restore(tmp_path / "buffer.ckpt", back)
    assert back.sampler.describe()["rollout_return"] == meta["rollout_return"]
    for b in (state, back):
        b.intake.ingest(make_episode(5, ret=1000.0, seq=150, start=0).encode())
    assert back.sampler.describe()["rollout_return"] == state.sampler.describe()["rollout_return"] == pytest.approx((sum(range(51, 150)) + 1000) / 100)
    # A non-finite mean in a reply is refused where the learner decodes it, as D_E's returns are.
    bad = P.BatchReply("not_ready", {"env_steps": 1, "rollout_return": float("nan")}, reason="warmup")
    with pytest.raises(P.ProtocolError, match="rollout_return"):
        P.BatchReply.decode(bad.encode())
