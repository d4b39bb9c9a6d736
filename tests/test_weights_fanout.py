"""The weights' fan-out budget (`--weights-fanout-mb-s`, issue 20 item 2): `FanoutPacer` against a clock
it is handed. A real run with a budget that holds publications back is in tests/test_weights_dtype.py."""

from __future__ import annotations

from silcr.common.fanout import FanoutPacer


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_publication_waits_until_the_last_ones_fanout_fits_the_budget():
    clock, actors = Clock(), [4]
    pacer = FanoutPacer(4_000.0, lambda: actors[0], clock)  # 4 actors x 1,000 bytes at 4,000 B/s: one a second
    assert pacer.offer(b"a" * 1000) == b"a" * 1000
    clock.now = 0.5
    assert pacer.offer(b"b" * 1000) is None and pacer.due() is None
    assert pacer.offer(b"c" * 1000) is None  # the newer set replaces the waiting one
    assert (pacer.held, pacer.replaced) == (2, 1)
    actors[0] = 8  # more actors: the same bytes cost twice the fan-out, so the next waits twice as long
    clock.now = 1.0
    assert pacer.due() == b"c" * 1000 and pacer.due() is None
    clock.now = 2.5
    assert pacer.offer(b"d" * 1000) is None
    clock.now = 3.0
    assert pacer.due() == b"d" * 1000


def test_the_final_publication_and_a_zero_budget_are_never_held():
    clock = Clock()
    pacer = FanoutPacer(1.0, lambda: 100, clock)
    pacer.offer(b"x" * 100)
    assert pacer.offer(b"last", final=True) == b"last" and pacer.waiting is None
    free = FanoutPacer(0.0, lambda: 10_000, clock)
    assert all(free.offer(bytes(10)) == bytes(10) for _ in range(100)) and free.held == 0


def test_the_traffic_stays_within_the_budget_however_fast_the_learner_publishes():
    clock, budget, size = Clock(), 1e6, 50_000
    actors = lambda: 5 + int(clock.now) % 20  # noqa: E731  actors come and go
    pacer = FanoutPacer(budget, actors, clock)
    sent = []
    for step in range(60_000):  # a publication every millisecond for a minute
        clock.now = step / 1000
        for payload in (pacer.offer(bytes(size)), pacer.due()):
            if payload is not None:
                sent.append((clock.now, actors() * len(payload)))
    traffic = sum(b for _, b in sent)
    assert traffic <= budget * 60 + max(b for _, b in sent), traffic  # at most one publication over
    assert traffic >= 0.9 * budget * 60  # and the budget is used, not wasted
    assert pacer.held > 0.95 * 60_000
