"""An actor's outbox (issue 63): what it sends, sends again and lets go of, by the buffer's acks."""

from __future__ import annotations

import time

from silcr.common import protocol as P
from silcr.common.outbox import Outbox, ep_bytes
from tests.conftest import make_episode


def _fill(outbox: Outbox, seqs) -> None:
    for seq in seqs:
        outbox.add(make_episode(4, seq=seq))


def _send(outbox: Outbox, came_back: bool = False) -> list[int]:
    due = outbox.due(time.monotonic(), came_back)
    for ep in due:
        outbox.mark_sent(ep)
    return [ep.seq for ep in due]


def test_episodes_are_kept_until_confirmed_and_sent_again_from_the_gap_the_buffer_names():
    outbox = Outbox(ack_timeout=60)
    _fill(outbox, range(5))
    assert _send(outbox) == [0, 1, 2, 3, 4]
    assert not outbox.anything_due(time.monotonic())  # all sent, none timed out
    assert outbox.take_ack(P.EpisodeAck(0, 0, confirmed=1)) == 2 and len(outbox) == 3
    # 2 was lost on the way: the buffer refused 3 and 4 and asks again from 2, once per gap.
    outbox.take_ack(P.EpisodeAck(0, 0, confirmed=1, resend_from=2))
    due = outbox.due(time.monotonic(), False)
    assert [e.seq for e in due] == [2, 3, 4] and {e.resend_from for e in due} == {2}
    for ep in due:
        outbox.mark_sent(ep)
    outbox.take_ack(P.EpisodeAck(0, 0, confirmed=1, resend_from=2))  # the refusal of 4, behind the first
    assert _send(outbox) == []
    assert outbox.stats()["episodes_resent"] == 3 and outbox.stats()["resend_rounds"] == 1
    outbox.take_ack(P.EpisodeAck(0, 0, confirmed=4))
    assert len(outbox) == 0 and outbox.bytes == 0 and outbox.confirmed == 5


def test_a_buffer_back_or_a_silent_one_gets_the_oldest_episode_as_a_probe():
    outbox = Outbox(ack_timeout=0.05)
    _fill(outbox, range(3))
    assert _send(outbox) == [0, 1, 2]
    assert _send(outbox, came_back=True) == [0]
    time.sleep(0.1)
    assert outbox.anything_due(time.monotonic())
    assert _send(outbox) == [0]  # no ack for 0.05 s: probed again, and the wait doubles
    assert not outbox.anything_due(time.monotonic())


def test_a_stopping_actor_sends_everything_unconfirmed_again_when_no_ack_comes():
    # The last episodes sent before a link dropped were lost, and a stopping actor sends no new one whose arrival
    # would show the buffer the gap: a probe would get back one episode per timeout, too few before it stops.
    outbox = Outbox(ack_timeout=60)
    _fill(outbox, range(5))
    assert _send(outbox) == [0, 1, 2, 3, 4]
    outbox.take_ack(P.EpisodeAck(0, 0, confirmed=1))
    outbox.hurry(0.05)
    assert _send(outbox) == []  # it waits for the ack first
    time.sleep(0.1)
    assert _send(outbox) == [2, 3, 4]
    assert outbox.stats()["episodes_resent"] == 3 and outbox.stats()["resend_rounds"] == 1
    outbox.take_ack(P.EpisodeAck(0, 0, confirmed=4))
    assert len(outbox) == 0


def test_the_outbox_is_full_at_its_bound_but_always_takes_one_episode():
    one = ep_bytes(make_episode(4))
    outbox = Outbox(limit_bytes=2 * one + 1)
    _fill(outbox, [0, 1])
    assert not outbox.full()
    _fill(outbox, [2])
    assert outbox.full()
    assert Outbox(limit_bytes=1).full() is False
    assert outbox.give_up() == (3, 0, 2) and len(outbox) == 0 and not outbox.full()


def test_looking_for_due_episodes_while_acks_arrive_in_another_thread_never_raises():
    """Zenoh's thread takes acks while the actor's thread asks `anything_due`: without the lock there, the outbox
    could empty or change between its two looks (StopIteration ended an actor in the scale bench; this test, on
    the code before, raised "OrderedDict mutated during iteration" within a second)."""
    import sys
    import threading

    box = Outbox()
    episodes = [make_episode(2, seq=i) for i in range(100_000)]
    done = threading.Event()

    def acks() -> None:
        for ep in episodes:
            if done.is_set():
                return
            box.add(ep)
            box.take_ack(P.EpisodeAck(0, 1, ep.seq))

    before = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as the interpreter can: the window is a few bytecodes
    thread = threading.Thread(target=acks)
    thread.start()
    try:
        end = time.monotonic() + 2.0
        while time.monotonic() < end and thread.is_alive():
            box.anything_due(time.monotonic())
    finally:
        done.set()
        thread.join()
        sys.setswitchinterval(before)
