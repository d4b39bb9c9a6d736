"""Labellers: how the rows of a batch get the rewards the learner trains on.

The algorithm registry (`silcr.common.algorithms`) names a labeller for each algorithm
(`Algorithm.labels`); `labeller_for` builds it. A labeller is told of every episode that
enters or leaves D_O and D_E (`entered`, `left`: the tables call it), says whether the
tables should copy the env's rewards into the batch (`copies_env_rewards`), and then
writes the labels of a composed batch (`label`):

    constant  SILCR and SQIL (paper eq. 3): 0 for every D_O row, 1 for every D_E row
    env       SAC and GASIL: the reward the actors' env paid, as stored
"""

from __future__ import annotations

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


LABELLERS: dict[str, type] = {"constant": ConstantLabels, "env": EnvLabels}


def labeller_for(algo: Algorithm) -> Labeller:
    return LABELLERS[algo.labels]()
