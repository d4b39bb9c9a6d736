"""The buffer's episode log (issue 63): what it holds is replayed after a crash, a torn last record is
ignored, checkpoints compact it, and a failed write stops acks until a checkpoint stands for it."""

from __future__ import annotations

import errno

import pytest

from silcr.buffer_service import snapshot
from silcr.buffer_service.episode_log import EpisodeLog, read, segments
from silcr.buffer_service.replay import ReplayState
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from tests.conftest import make_episode

ENV = "InvertedPendulum-v5"


def _state() -> ReplayState:
    return ReplayState(Config(run="log", env=ENV), EnvSpec.of(ENV))


def _episodes(n: int, first: int = 0):
    out = []
    for seq in range(first, first + n):
        ep = make_episode(3 + seq % 4, ret=float(seq), seq=seq, start=10.0 * seq)
        ep.incarnation, ep.resend_from = 5, seq
        out.append(ep)
    return out


def test_the_log_replays_every_stored_episode_in_order_and_ignores_a_torn_last_record(tmp_path):
    log = EpisodeLog(tmp_path / "log")
    sent = _episodes(6)
    for ep in sent:
        log.append(ep.encode())
    assert log.flush() and log.confirms()
    # Killed mid-write: half a record at the end, never acknowledged.
    path = segments(tmp_path / "log")[0]
    path.write_bytes(path.read_bytes() + sent[0].encode()[:20])
    again = list(read(tmp_path / "log", _state().limits))
    assert [e.seq for e in again] == [0, 1, 2, 3, 4, 5]
    assert all((a.obs == b.obs).all() and a.episode_return == b.episode_return for a, b in zip(again, sent))
    # A flipped bit in the last record's observations (still a finite number, still a valid episode):
    # its CRC no longer matches, so it ends the segment there too.
    data = bytearray(path.read_bytes())
    at = data.rfind(sent[5].obs.tobytes())
    data[at + 4] ^= 0x01  # the lowest mantissa byte of a float32
    path.write_bytes(bytes(data))
    assert [e.seq for e in read(tmp_path / "log", _state().limits)] == [0, 1, 2, 3, 4]


def test_replay_after_a_checkpoint_stores_only_what_the_checkpoint_lacks(tmp_path):
    """A checkpoint rotates the log; until it is on disk the older segment stays, and replaying both over
    the checkpoint stores each episode once."""
    state, log = _state(), EpisodeLog(tmp_path / "log")
    for ep in _episodes(4):
        state.intake.store(ep)
        log.append(ep.encode())
    segment = log.rotate()  # the checkpoint is taken here ...
    snap = snapshot.take(state)
    for ep in _episodes(3, first=4):
        state.intake.store(ep)
        log.append(ep.encode())
    log.flush()
    snapshot.write(tmp_path / "buffer.ckpt", snap)  # ... and written; a crash before `checkpoint_written`
    assert len(segments(tmp_path / "log")) == 2
    restored = _state()
    snapshot.restore(tmp_path / "buffer.ckpt", restored)
    replayed = sum(restored.intake.replay(ep) for ep in read(tmp_path / "log", restored.limits))
    assert replayed == 3 and restored.intake.episodes_received == 7
    assert [e.seq for e in restored.fifo.episodes()] == list(range(7))
    log.checkpoint_written(segment)
    assert [p.stem for p in segments(tmp_path / "log")] == [str(segment)]  # the older segment is gone


def test_a_record_the_log_cannot_read_is_a_gap_the_replay_counts_missing_and_steps_over(tmp_path):
    """A corrupt record in the middle ends its segment's reading; the confirmed episodes of the next segment
    are stored all the same (a buffer that refused them would not start)."""
    log = EpisodeLog(tmp_path / "log")
    for ep in _episodes(3):
        log.append(ep.encode())
    log.rotate()
    for ep in _episodes(2, first=3):
        log.append(ep.encode())
    log.close(checkpointed=False)
    first = segments(tmp_path / "log")[0]
    data = bytearray(first.read_bytes())
    data[data.rfind(_episodes(3)[1].obs.tobytes()) + 4] ^= 0x01  # seq 1's record: 1 and 2 are not read
    first.write_bytes(bytes(data))
    state = _state()
    assert sum(state.intake.replay(ep) for ep in read(tmp_path / "log", state.limits)) == 3
    assert [e.seq for e in state.fifo.episodes()] == [0, 3, 4] and state.intake.episodes_missing == 2


def test_a_failed_write_stops_acks_until_a_checkpoint_taken_after_it_is_on_disk(tmp_path, monkeypatch):
    log = EpisodeLog(tmp_path / "log")
    eps = _episodes(3)
    log.append(eps[0].encode())
    assert log.flush()

    def full(*_a):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(log._file, "write", full)
    log.append(eps[1].encode())  # this one is not in the log: nothing after it may be confirmed by the log
    assert not log.flush() and log.failures == 1
    log.append(eps[2].encode())  # not written at all while the chain is broken
    assert log.appended == 1
    segment = log.rotate()  # a checkpoint of everything stored is taken ...
    log.append(eps[2].encode())
    assert not log.flush()  # ... but acks wait until it is on disk
    log.checkpoint_written(segment)
    assert log.flush() and log.confirms()
    assert log.stats()["episode_log_failures"] == 1


@pytest.mark.parametrize("checkpointed", [True, False])
def test_closing_removes_the_log_only_when_the_final_checkpoint_holds_it(tmp_path, checkpointed):
    log = EpisodeLog(tmp_path / "log")
    log.append(_episodes(1)[0].encode())
    log.flush()
    log.close(checkpointed)
    assert bool(segments(tmp_path / "log")) is not checkpointed
