"""Learning is tested: if SILCR stops learning, this fails.

Task: InvertedPendulum-v5 with the episodic reward (0 each step, the episode's
length at its end). A random policy balances for about 5 steps (return about 5);
the full distributed system (router, buffer, learner, actor processes over Zenoh)
with small networks and the default tau (0.005) reached 1000 by 20,000
environment steps, and the same run with `--single-process` (one process, no
Zenoh) reached 304, in about 1 minute each on the 2-core CPU machine
(docs/testing.md). Both launchers must learn.

What it catches: a broken learner update, broken weight distribution to the
actors, broken transitions (observations, actions, terminal flags) or a stalled
pipeline. What it does not catch: on this task SAC's entropy bonus alone is a
survival reward, so with every reward forced to 0 the agent still learned
(measured: the test passed with that mutation). The constant 0/1 rewards are
checked by tests/test_buffers.py (batch composition) and tests/test_sac.py
(r = 1 on D_E states lifts their Q above D_O's). See docs/testing.md.
"""

from __future__ import annotations

import pytest

from tests.helpers import free_port, train_to_the_end

RANDOM_RETURN_CEILING = 20.0  # the untrained policy's evaluation must be below this
BEST_RETURN_FLOOR = 100.0  # 20x the random policy's return of about 5
FINAL_RETURN_FLOOR = 50.0  # mean of the last two evaluations: 10x random (single evaluations are noisy)


@pytest.mark.slow
@pytest.mark.parametrize("launcher, algo", [("distributed", "silcr"), ("single-process", "silcr"),
                                            ("single-process", "ircr")])
def test_silcr_learns_inverted_pendulum_from_episodic_reward(tmp_path, launcher, algo):
    """IRCR too, through the same pipeline. On this task every episode's credit is 1 (one per
    step), so IRCR's labels are all 0 (test_ircr.py) and what it learns from is SAC's entropy
    bonus: this checks its plumbing; test_ranking.py checks that its label leads somewhere."""
    how = ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"] if launcher == "distributed" else ["--single-process"]
    rows, procs = train_to_the_end(
        tmp_path, "learning", *how, "--env", "InvertedPendulum-v5", "--algo", algo,
        "--actors", "2", "--seed", "1", "--total-steps", "20000", "--learning-starts", "1000",
        "--hidden", "64", "64", "--eval-interval", "3000", "--eval-episodes", "5",
    )
    returns = [float(r["eval_return"]) for r in rows]
    assert returns[0] < RANDOM_RETURN_CEILING, returns
    assert max(returns) >= BEST_RETURN_FLOOR, f"{algo} did not learn: eval returns {returns}"
    assert sum(returns[-2:]) / 2 >= FINAL_RETURN_FLOOR, f"{algo} did not keep what it learned: eval returns {returns}"
    assert rows[-1]["q_bound_exceeded"] == "0" and "diverging" not in procs.log("train")  # healthy critics
    assert procs.orphans == []