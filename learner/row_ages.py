"""How old the rows the learner trains on are: the policy lag of D_O's rows, the age of D_E's.

Every row carries the policy version that acted it. A reply's D_O rows lag the learner's current
version by a few versions in a healthy run (the actors keep up); D_E's rows are older by design
(the best episodes so far). Both are published as means over the last 200 replies.
"""

from __future__ import annotations

import collections

import numpy as np

from silcr.common import protocol as P

#: replies the means are taken over
WINDOW = 200


def _mean_lag(current: int, versions: np.ndarray) -> float | None:
    known = versions[versions >= 0]  # -1: acted before any learner weights arrived
    return float(current - known.mean()) if known.size else None


class RowAges:
    def __init__(self) -> None:
        self.policy_lag: collections.deque[float] = collections.deque(maxlen=WINDOW)  # D_O rows only
        self.expert_age: collections.deque[float] = collections.deque(maxlen=WINDOW)  # D_E rows

    def note(self, reply: P.BatchReply, policy_version: int) -> None:
        """The ages of an `ok` reply's rows, its first `online_rows` of each batch from D_O, the rest from D_E."""
        online, expert = reply.header.by_table(reply.batch.policy_version)
        if (lag := _mean_lag(policy_version, online)) is not None:
            self.policy_lag.append(lag)
        if expert.size and (age := _mean_lag(policy_version, expert)) is not None:
            self.expert_age.append(age)

    def stats(self) -> dict[str, float | None]:
        return {"policy_lag_mean": float(np.mean(self.policy_lag)) if self.policy_lag else None,
                "expert_age_mean": float(np.mean(self.expert_age)) if self.expert_age else None}
