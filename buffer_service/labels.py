"""Labellers: how the rows of a batch get the rewards the learner trains on.

The algorithm registry (`silcr.common.algorithms`) names a labeller for each algorithm
(`Algorithm.labels`); `labeller_for` builds it. A labeller is told of every episode that
enters or leaves D_O and D_E (`entered`, `left`: the tables call it), says whether the
tables should copy the env's rewards into the batch (`copies_env_rewards`), and then
writes the labels of a composed batch (`label`):

    constant  SILCR and SQIL (paper eq. 3): 0 for every D_O row, 1 for every D_E row
    env       SAC and GASIL: the reward the actors' env paid, as stored
    credit    IRCR: the row's episode's return per step, min-max normalised over the
              episodes now in D_O and D_E
"""

from __future__ import annotations

import heapq
from collections import Counter
from typing import Protocol

import numpy as np

from silcr.common.algorithms import Algorithm
from silcr.common.protocol import Episode

from .storage import Drawn


class Labeller(Protocol):
    #: the tables copy the env's stored rewards into the batch before `label` is called
    copies_env_rewards: bool

    def entered(self, ep: Episode) -> None: ...

    def left(self, ep: Episode) -> None: ...

    def label(self, rewards: np.ndarray, online: Drawn, expert: Drawn | None) -> None:
        """Write the labels into `rewards` (batches x batch size): each batch's first
        `online.slots.size / batches` rows come from D_O (`online`), the rest from D_E (`expert`)."""


class ConstantLabels:
    """Paper eq. 3: r = 0 for D_O samples, r = 1 for D_E samples, whatever the env paid."""

    copies_env_rewards = False

    def entered(self, ep: Episode) -> None:
        pass

    def left(self, ep: Episode) -> None:
        pass

    def label(self, rewards: np.ndarray, online: Drawn, expert: Drawn | None) -> None:
        n_online = online.slots.size // rewards.shape[0]
        rewards[:, :n_online] = 0.0
        rewards[:, n_online:] = 1.0


class EnvLabels(ConstantLabels):
    """The env's reward as the actors' env paid it (dense or episodic): already in the batch."""

    copies_env_rewards = True

    def label(self, rewards: np.ndarray, online: Drawn, expert: Drawn | None) -> None:
        pass


class CreditLabels(ConstantLabels):
    """IRCR's guidance reward (Gangwani, Zhou and Peng 2020, Algorithm 2, line 18, as the official code has it).

    Every transition of an episode gets the episode's credit c = return / length (with
    the episodic reward, the mean reward per step), normalised to [0, 1] by the lowest
    and highest credit among the episodes now in D_O and D_E:

        r = (c - c_min) / (c_max - c_min)      (0 while every stored episode has the same credit)

    c_min and c_max are kept as episodes enter and leave, never by rescanning rows: a
    count per credit value (an episode in both tables counts twice) and two heaps of
    credit values whose stale tops (counts at zero) are dropped when looked at.
    """

    copies_env_rewards = False

    def __init__(self) -> None:
        self._count: Counter[float] = Counter()
        self._low: list[float] = []  # min-heap of credits
        self._high: list[float] = []  # min-heap of negated credits

    @staticmethod
    def credit(episode_return: float | np.ndarray, length: int | np.ndarray) -> float | np.ndarray:
        return episode_return / length

    def entered(self, ep: Episode) -> None:
        c = self.credit(ep.episode_return, ep.length)
        if self._count[c] == 0:
            heapq.heappush(self._low, c)
            heapq.heappush(self._high, -c)
        self._count[c] += 1
        if len(self._low) > 2 * len(self._count) + 64:  # many stale values: rebuild from the live ones
            self._low = list(self._count)
            self._high = [-c for c in self._count]
            heapq.heapify(self._low)
            heapq.heapify(self._high)

    def left(self, ep: Episode) -> None:
        c = self.credit(ep.episode_return, ep.length)
        self._count[c] -= 1
        if self._count[c] == 0:
            del self._count[c]

    def credit_range(self) -> tuple[float, float] | None:
        """(c_min, c_max) over the episodes now stored, or None when there are none."""
        while self._low and self._low[0] not in self._count:
            heapq.heappop(self._low)
        while self._high and -self._high[0] not in self._count:
            heapq.heappop(self._high)
        return (self._low[0], -self._high[0]) if self._low else None

    def label(self, rewards: np.ndarray, online: Drawn, expert: Drawn | None) -> None:
        c_min, c_max = self.credit_range()
        span = c_max - c_min
        batches = rewards.shape[0]
        n_online = online.slots.size // batches
        for drawn, columns in ((online, slice(0, n_online)), (expert, slice(n_online, None))):
            if drawn is None:
                continue
            c = self.credit(drawn.episode_return, drawn.episode_length).reshape(batches, -1)
            rewards[:, columns] = (c - c_min) / span if span > 0 else 0.0


LABELLERS: dict[str, type] = {"constant": ConstantLabels, "env": EnvLabels, "credit": CreditLabels}


def labeller_for(algo: Algorithm) -> Labeller:
    return LABELLERS[algo.labels]()
