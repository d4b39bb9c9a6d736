"""SamplesPerInsertLimiter: warm-up, the window, hysteresis, and that it can never deadlock."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from silcr.buffer_service.rate_limiter import SamplesPerInsertLimiter


def test_no_samples_during_warmup_then_one_update_per_step():
    lim = SamplesPerInsertLimiter(1.0, min_size_to_sample=100, tolerance=10)
    lim.record_insert(100)
    assert lim.warming_up() and lim.available() == 0  # the official code waits for *more than* 100
    lim.record_insert(1)
    assert not lim.warming_up()
    # The learner may be `tolerance` updates ahead of one update per step after warm-up.
    assert lim.available() == 11
    lim.record_sample(11)
    assert lim.available() == 0
    lim.record_insert(5)
    assert lim.available() == 5


def test_actors_pause_above_window_and_resume_at_centre():
    lim = SamplesPerInsertLimiter(1.0, min_size_to_sample=100, tolerance=10)
    lim.record_insert(110)
    assert not lim.inserts_paused()
    lim.record_insert(1)
    assert lim.inserts_paused()  # 11 ahead > tolerance
    lim.record_sample(5)
    assert lim.inserts_paused()  # hysteresis: still 6 ahead
    lim.record_sample(6)
    assert not lim.inserts_paused()  # back at the centre


def test_a_budget_spent_during_the_warm_up_pauses_the_actors_at_the_budget():
    """A run shorter than --learning-starts (learn(4000) at the default 10,240): the actors ran unthrottled until
    the learner joined, to 11,441 env steps. No update can need more than the budget."""
    lim = SamplesPerInsertLimiter(1.0, min_size_to_sample=10_240, tolerance=2000, final_inserts=4000)
    lim.record_insert(3999)
    assert lim.warming_up() and not lim.inserts_paused()
    lim.record_insert(1)
    assert lim.inserts_paused()
    # without a budget, the warm-up never pauses (the learner is what the window waits for)
    free = SamplesPerInsertLimiter(1.0, min_size_to_sample=10_240, tolerance=2000)
    free.record_insert(10_240)
    assert not free.inserts_paused()


def test_no_throttle_never_pauses():
    lim = SamplesPerInsertLimiter(1.0, min_size_to_sample=0, tolerance=1, throttle_inserts=False)
    lim.record_insert(10**6)
    assert not lim.inserts_paused()


def test_ratio_other_than_one():
    lim = SamplesPerInsertLimiter(0.25, min_size_to_sample=0, tolerance=1)
    lim.record_insert(40)
    assert lim.available() == 11  # 40 * 0.25 + 1
    lim.record_sample(11)
    assert lim.observed_samples_per_insert() == pytest.approx(11 / 40)


@pytest.mark.parametrize("kwargs", [{"samples_per_insert": 0}, {"tolerance": 0.5}, {"min_size_to_sample": -1}])
def test_invalid_settings_raise(kwargs):
    with pytest.raises(ValueError):
        SamplesPerInsertLimiter(**kwargs)


@settings(max_examples=200, deadline=None)
@given(
    spi=st.sampled_from([0.1, 0.5, 1.0, 2.0, 8.0]),
    min_size=st.integers(0, 500),
    tol=st.floats(1.0, 300.0),
    ops=st.lists(st.tuples(st.booleans(), st.integers(1, 200)), max_size=200),
)
def test_never_both_blocked(spi, min_size, tol, ops):
    """Whatever happened before, either actors may insert or the learner may sample."""
    lim = SamplesPerInsertLimiter(spi, min_size, tol)
    for is_insert, n in ops:
        if is_insert:
            if not lim.inserts_paused():
                lim.record_insert(n)
        else:
            lim.record_sample(min(n, lim.available()))
        assert not (lim.inserts_paused() and lim.available() == 0)


def test_over_the_budgets_last_stretch_actors_keep_pace_instead_of_running_a_window_ahead():
    """Issue 41: with a budget, the last 2 * tolerance / spi inserts pause the actors whenever they are ahead of the
    ratio at all (no hysteresis), so the learner's last updates never wait out a whole window on static tables."""
    lim = SamplesPerInsertLimiter(1.0, min_size_to_sample=10, tolerance=100, final_inserts=1000)
    lim.record_insert(700)  # mid-run: a window ahead before pausing, then paused until back at the centre
    lim.record_sample(700 - 10 - 100)
    assert not lim.at_the_end() and not lim.inserts_paused()
    lim.record_insert(1)
    assert lim.inserts_paused()
    lim.record_sample(50)
    assert lim.inserts_paused()  # hysteresis
    lim.record_insert(100)  # 801 inserts: inside the last 200 of the budget
    assert lim.at_the_end() and lim.inserts_paused()
    while lim.error > lim.centre:  # the learner catches up ...
        assert lim.inserts_paused()
        lim.record_sample(1)
    assert not lim.inserts_paused()  # ... and the actors resume at once, one episode at a time
    lim.record_insert(5)
    assert lim.inserts_paused()
    lim.record_sample(5)
    assert not lim.inserts_paused()
    lim.record_insert(300)  # past the budget (the learner still has updates due): still in step
    assert lim.at_the_end() and lim.inserts_paused()
    # without a budget the hysteresis holds to the end
    free = SamplesPerInsertLimiter(1.0, min_size_to_sample=10, tolerance=100)
    free.record_insert(1000)
    free.record_sample(1000 - 10 - 101)
    assert free.inserts_paused()
    free.record_sample(50)
    assert free.inserts_paused()
