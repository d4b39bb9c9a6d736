"""The learner's gradient steps: SAC on every batch, and GASIL's discriminator first when the algorithm has one.

`Update.train(reply, updates_done)` runs one SAC update per batch of a buffer
reply: `sac.py`'s for continuous actions, `sac_discrete.py`'s for discrete ones (the
env's action kind decides, whatever the algorithm). With a discriminator (`Algorithm.discriminator`, `gasil.py`) it first
steps the discriminator on the reply's D_E and recent D_O rows (every
`--disc-interval` updates), then shapes that batch's rewards with r_D from the
discriminator as it is now, never stored. Everything it holds saves and restores
itself (`state`, `restore`): the checkpoint's "sac" and "gasil" sections.
"""

from __future__ import annotations

import logging
import time
import warnings
from typing import Any

import numpy as np
import torch

from silcr.common import protocol as P
from silcr.common.algorithms import LABEL_MAX, algorithm
from silcr.common.config import Config, critics_of
from silcr.common.envs import EnvSpec
from silcr.common.process_env import openmp_wait

from . import denormals
from .gasil import Gasil, GasilHyper
from .sac import Sac, SacHyper, SacState, as_floats
from .sac_discrete import DiscreteSac, DiscreteSacHyper
from .threads import Retimer, choose_threads, usable_cores

log = logging.getLogger("learner")


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: CUDA is not available on this machine")
    return torch.device(name)


def to_tensor(a: np.ndarray, device: torch.device) -> torch.Tensor:
    """A reply's array as a tensor on `device`, with no copy on a CPU.

    Arrays decoded from a message are read-only views of it (zero-copy), and torch
    warns about tensors over read-only memory because writing to them would be
    undefined. The update only reads its batch (the flags become new float tensors),
    so that one warning is silenced here instead of paying for a copy of every batch.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable", category=UserWarning)
        return torch.from_numpy(a).to(device, non_blocking=True)


def synthetic_batch(spec: EnvSpec, n: int) -> tuple[torch.Tensor, ...]:
    """A batch of `n` random rows of `spec`'s shapes, for timing the update (`Sac.update`'s arguments).

    Drawn from its own generator, so timing an update changes nothing a run draws.
    """
    g = torch.Generator().manual_seed(0)
    actions = (torch.randint(0, spec.n_actions, (n, 1), generator=g) if spec.discrete
               else torch.rand(n, spec.act_dim, generator=g) * 2 - 1)
    return (torch.randn(n, spec.obs_dim, generator=g), actions, torch.randint(0, 2, (n,), generator=g).float(),
            torch.randn(n, spec.obs_dim, generator=g), torch.zeros(n), torch.zeros(n))


class Update:
    """The networks, the optimisers and the gradient steps of one learner."""

    def __init__(self, cfg: Config, spec: EnvSpec) -> None:
        self.cfg = cfg
        self.device = pick_device(cfg.device)
        self.spec = spec
        self.retimer: Retimer | None = None  # set when the threads are chosen by timing
        self.torch_threads = self._set_threads(spec)
        torch.manual_seed(cfg.seed)  # after the thread probe, so that it changes nothing the run draws
        self.sac = self._new_sac()
        self.gasil: Gasil | None = None
        if algorithm(cfg.algo).discriminator:
            ghp = GasilHyper(cfg.gasil_alpha, cfg.gasil_reward, tuple(cfg.disc_hidden), cfg.disc_lr, cfg.disc_grad_penalty,
                             cfg.disc_warmup)
            self.gasil = Gasil(spec.obs_dim, spec.act_dim, ghp, self.device)
        self._last: dict[str, torch.Tensor] = {}
        self._disc_last: dict[str, torch.Tensor] = {}

    def _new_sac(self) -> SacState:
        """The SAC update for the env's action kind, with this run's hyperparameters."""
        cfg, spec = self.cfg, self.spec
        critic_norm, q_target_clip = critics_of(cfg)
        # --q-target-clip bound: the labels' largest value (config validation refuses it for env rewards)
        target_reward_max = LABEL_MAX if q_target_clip == "bound" else None
        if spec.discrete:
            if cfg.bc_weight > 0:
                raise ValueError(f"--bc-weight: {spec.env_id} has discrete actions; the behaviour-cloning term is "
                                 f"for continuous ones")
            if cfg.target_entropy_per_dim != -1.0:
                raise ValueError(f"--target-entropy-per-dim: {spec.env_id} has discrete actions; set "
                                 f"--target-entropy-scale for them")
            dhp = DiscreteSacHyper(cfg.gamma, cfg.tau, cfg.lr, cfg.grad_clip, cfg.init_alpha, cfg.target_entropy_scale,
                                   cfg.time_limit_terminal, cfg.absorbing_terminal, critic_norm, target_reward_max)
            return DiscreteSac(spec.obs_dim, spec.n_actions, cfg.hidden, dhp, self.device)
        target_entropy = cfg.target_entropy_per_dim * spec.act_dim  # SAC's -|A| by default
        hp = SacHyper(cfg.gamma, cfg.tau, cfg.lr, cfg.grad_clip, cfg.init_alpha, target_entropy, cfg.time_limit_terminal,
                      cfg.tanh_log_prob, cfg.absorbing_terminal, critic_norm, target_reward_max, cfg.bc_weight)
        return Sac(spec.obs_dim, spec.act_dim, cfg.hidden, hp, self.device)

    def _set_threads(self, spec: EnvSpec) -> int:
        """`--torch-threads`, or on a CPU with several cores the faster of 1 and all, timed (`threads.py`)."""
        cores = usable_cores()
        if self.cfg.torch_threads or self.device.type != "cpu" or cores <= 1:
            torch.set_num_threads(self.cfg.torch_threads or torch.get_num_threads())
            return torch.get_num_threads()
        probe = self._new_sac()  # a throwaway copy
        batch = synthetic_batch(spec, self.cfg.batch_size)
        with denormals.flushed(self.device, not self.cfg.keep_denormals):  # timed as the update will run (denormals.py)
            best, times = choose_threads(lambda: probe.update(*batch), cores)
        torch.set_num_threads(best)
        self.retimer = Retimer(sorted(times), best)
        log.info("torch threads: %d (timed the update: %s; idle threads %s; re-timed every %.0f s on the run's "
                 "updates; --torch-threads N sets it)", best,
                 ", ".join(f"{k} thread{'s' if k > 1 else ''} {1000 * t:.2f} ms" for k, t in times.items()),
                 openmp_wait(), self.retimer.every_s)
        return best

    def sample_request(self) -> P.SampleRequest:
        """What to ask the buffer for: a discriminator also wants its rows."""
        cfg = self.cfg
        if self.gasil is None:
            return P.SampleRequest(cfg.batches_per_request, cfg.batch_size)
        return P.SampleRequest(cfg.batches_per_request, cfg.batch_size, cfg.disc_batch_size, cfg.recent_window)

    def train(self, reply: P.BatchReply, updates_done: int) -> int:
        """One update per batch of `reply` (`updates_done` updates came before); how many it made."""
        header = reply.header  # checked by the learner (`BatchHeader.check`) before it gets here
        n, size, expert_from = header.batches, header.batch_size, header.expert_from
        batch = reply.batch.map(lambda a: to_tensor(a, self.device))
        disc = reply.disc.map(lambda a: to_tensor(a, self.device)) if reply.disc is not None else None
        term, trunc = batch.terminated.float(), batch.truncated.float()
        t0 = time.perf_counter()
        with denormals.flushed(self.device, not self.cfg.keep_denormals):  # a fifth of a CPU update's time otherwise (denormals.py)
            for b in range(n):
                s = slice(b * size, (b + 1) * size)
                rewards = batch.rewards[s]
                if self.gasil is not None:
                    if (updates_done + b) % self.cfg.disc_interval == 0:
                        d = disc.rows(b, self.cfg.disc_batch_size)
                        self._disc_last = self.gasil.update(d.expert_obs, d.expert_actions, d.recent_obs, d.recent_actions)
                    # r_D from the discriminator as it is now, for this batch only (never stored)
                    rewards, r_d_mean = self.gasil.shape(rewards, batch.obs[s], batch.actions[s])
                self._last = self.sac.update(batch.obs[s], batch.actions[s], rewards, batch.next_obs[s], term[s], trunc[s],
                                             expert_from)
                if self.gasil is not None:
                    self._last |= self._disc_last | {"gasil_reward_mean": r_d_mean}
        if self.retimer is not None:
            self.torch_threads = self.retimer.observe(n, time.perf_counter() - t0)
        return n

    # -- reporting -------------------------------------------------------------------
    @property
    def alpha(self) -> float:
        return self.sac.alpha

    def stats(self) -> dict[str, float]:
        """The last update's statistics and the divergence count; reading them waits for the device, so only when reporting."""
        out: dict[str, float] = as_floats(self._last)
        out["q_bound_exceeded"] = int(self.sac.q_bound_exceeded)
        return out

    def stat_names(self) -> list[str]:
        return [*self._last, "q_bound_exceeded"] if self._last else []

    def weights(self, version: int, incarnation: int, sent_at: float, wire_dtype: str = "float32") -> P.Weights:
        return P.Weights(version, self.sac.actor_arrays(), self.sac.arch(), sent_at=sent_at, incarnation=incarnation,
                         action_kind=self.spec.action_kind, wire_dtype=wire_dtype)

    # -- checkpoints -------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        out = {"sac": self.sac.state_dict()}
        if self.gasil is not None:
            out["gasil"] = self.gasil.state_dict()
        return out

    def restore(self, payload: dict[str, Any], where: object) -> None:
        if payload["sac"]["arch"] != self.sac.arch():
            raise ValueError(f"checkpoint networks {payload['sac']['arch']} do not match this run's {self.sac.arch()}")
        self.sac.load_state_dict(payload["sac"])
        if self.gasil is not None:
            if payload.get("gasil") is None:
                raise ValueError(f"checkpoint {where} holds no GASIL discriminator (written by another --algo)")
            self.gasil.load_state_dict(payload["gasil"])
