"""The learner: pull mixed batches, update SAC, push weights, evaluate, record, checkpoint.

`Learner` is the bookkeeping around `Sac`: `step(batch)` trains on one reply's
batches and keeps the counters, the weights schedule, checkpoints and the
evaluation schedule; it needs no network (tests drive it directly, and
`silcr train --single-process` drives it with in-process clients).
`run_learner` is the process over Zenoh: a loop over a `ZenohBatchStream`
(several sample queries in flight; not-ready replies, retries and buffer restarts
handled there) that publishes weights through a `ZenohWeightsServer` and stats on
the learner's stats key.
"""

from __future__ import annotations

import collections
import logging
import time
import warnings
from typing import Any

import numpy as np
import torch

from silcr.common import protocol as P
from silcr.common.clients import (Shutdown, StatsPublisher, WeightsServer, ZenohBatchStream, ZenohWeightsServer,
                                  stop_on_shutdown)
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, session_config

from .checkpoint import load_checkpoint, save_checkpoint
from .evaluate import evaluate
from .gasil import Gasil, GasilHyper
from .progress import DIVERGENCE_COLUMNS, EXPERT_COLUMNS, GASIL_COLUMNS, ProgressLog
from .sac import Sac, SacHyper, as_floats

log = logging.getLogger("learner")


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: CUDA is not available on this machine")
    return torch.device(name)


def batch_tensors(arrays: dict[str, np.ndarray], device: torch.device) -> dict[str, torch.Tensor]:
    """A reply's arrays as tensors on `device`, with no copy on a CPU.

    Arrays decoded from a message are read-only views of it (zero-copy), and torch
    warns about tensors over read-only memory because writing to them would be
    undefined. The update only reads its batch (the flags become new float tensors),
    so that one warning is silenced here instead of paying for a copy of every batch.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The given NumPy array is not writable", category=UserWarning)
        return {k: torch.from_numpy(v).to(device, non_blocking=True) for k, v in arrays.items() if k != "policy_version"}


def _mean_lag(current: int, versions: np.ndarray) -> float | None:
    known = versions[versions >= 0]  # -1: acted before any learner weights arrived
    return float(current - known.mean()) if known.size else None


class BufferMismatch(RuntimeError):
    """The buffer service's batches are not what this learner's --algo needs (it runs another --algo)."""


class Learner:
    """SAC plus everything a run keeps around it: counters, weights, evaluations, records, checkpoints."""

    def __init__(self, cfg: Config, spec: EnvSpec, weights: WeightsServer) -> None:
        self.cfg, self.spec = cfg, spec
        self.weights_server = weights
        self.device = pick_device(cfg.device)
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        hp = SacHyper(cfg.gamma, cfg.tau, cfg.lr, cfg.grad_clip, cfg.init_alpha, None, cfg.time_limit_terminal,
                      cfg.tanh_log_prob)
        self.sac = Sac(spec.obs_dim, spec.act_dim, cfg.hidden, hp, self.device)
        self.gasil: Gasil | None = None
        if cfg.algo == "gasil":
            ghp = GasilHyper(cfg.gasil_alpha, cfg.gasil_reward, tuple(cfg.disc_hidden), cfg.disc_lr, cfg.disc_grad_penalty,
                             cfg.disc_warmup)
            self.gasil = Gasil(spec.obs_dim, spec.act_dim, ghp, self.device)
        self.incarnation = P.new_incarnation()
        self.updates = 0
        self.policy_version = 0
        self.env_steps = 0
        self.next_eval = 0
        self.evals = 0
        self.last_eval_return: float | None = None
        self.last_eval_updates = -1
        self.checkpoint_path = cfg.run_dir / "checkpoints" / "learner.pt"
        # --resume continues from a checkpoint when there is one, so the same command
        # serves a first start and every restart (launcher, sweep, docker restart policy).
        self.resumed = cfg.resume and self.checkpoint_path.exists()
        if self.resumed:
            self._restore(load_checkpoint(self.checkpoint_path))
        elif cfg.resume:
            log.info("--resume: no checkpoint at %s yet; starting fresh", self.checkpoint_path)
        self.next_checkpoint = (self.updates // cfg.checkpoint_interval + 1) * cfg.checkpoint_interval
        cfg.run_dir.mkdir(parents=True, exist_ok=True)
        self.progress = ProgressLog(cfg.run_dir, resume=self.resumed)
        self.started = time.monotonic()
        self.update_time = 0.0
        self.buffer_meta: dict[str, Any] = {}  # the latest reply's description of the buffer (D_E's returns)
        self.policy_lag: collections.deque[float] = collections.deque(maxlen=200)  # D_O rows only
        self.expert_age: collections.deque[float] = collections.deque(maxlen=200)  # D_E rows
        self._last_stats: dict[str, torch.Tensor] = {}
        self._disc_stats: dict[str, torch.Tensor] = {}  # the last discriminator update's

    # -- checkpoints -------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return {
            "updates": self.updates,
            "policy_version": self.policy_version,
            "env_steps": self.env_steps,
            "next_eval": self.next_eval,
            "evals": self.evals,
            "last_eval_return": self.last_eval_return,
        }

    def _restore(self, payload: dict) -> None:
        if payload["sac"]["arch"] != self.sac.arch():
            raise ValueError(f"checkpoint networks {payload['sac']['arch']} do not match this run's {self.sac.arch()}")
        self.sac.load_state_dict(payload["sac"])
        if self.gasil is not None:
            if "gasil" not in payload:
                raise ValueError(f"checkpoint {self.checkpoint_path} holds no GASIL discriminator (written by another --algo)")
            self.gasil.load_state_dict(payload["gasil"])
        c = payload["counters"]
        self.updates, self.policy_version, self.env_steps = c["updates"], c["policy_version"], c["env_steps"]
        self.next_eval, self.evals, self.last_eval_return = c["next_eval"], c["evals"], c["last_eval_return"]
        log.info("resumed from %s: %d updates, policy version %d", self.checkpoint_path, self.updates, self.policy_version)

    def checkpoint(self) -> None:
        t0 = time.monotonic()
        payload = {"sac": self.sac.state_dict(), "counters": self.counters(), "config": self.cfg.to_dict()}
        if self.gasil is not None:
            payload["gasil"] = self.gasil.state_dict()
        save_checkpoint(self.checkpoint_path, payload)
        log.info("checkpoint at %d updates written in %.2fs", self.updates, time.monotonic() - t0)

    # -- weights and evaluation -----------------------------------------------------
    def weights(self) -> P.Weights:
        return P.Weights(self.policy_version, self.sac.actor_arrays(), self.sac.arch(), sent_at=time.time(),
                         incarnation=self.incarnation)

    def publish_weights(self) -> None:
        self.weights_server.publish(self.weights())

    def evaluate(self) -> None:
        """Evaluate the deterministic policy and write a progress row."""
        if self.cfg.eval_episodes == 0:
            return
        t0 = time.monotonic()
        mean, std, length = evaluate(self.weights(), self.spec, self.cfg.eval_episodes,
                                     self.cfg.seed + 1_000_000 + 1_000 * self.evals)
        self.evals += 1
        self.last_eval_return = mean
        self.last_eval_updates = self.updates
        elapsed = time.monotonic() - self.started
        losses = self.last_losses
        self.progress.row(
            {
                "time": round(elapsed, 3),
                "env_steps": self.env_steps,
                "updates": self.updates,
                "policy_version": self.policy_version,
                "eval_return": mean,
                "eval_return_std": std,
                "eval_length": length,
                "alpha": self.sac.alpha,
                "critic_loss": losses.get("critic_loss", float("nan")),
                "actor_loss": losses.get("actor_loss", float("nan")),
                "updates_per_s": self.updates / max(elapsed, 1e-9),
                **{k: losses.get(k, float("nan")) for k in DIVERGENCE_COLUMNS + GASIL_COLUMNS},
                **{k: self.buffer_meta.get(k) for k in EXPERT_COLUMNS},
            }
        )
        log.info("eval at %d env steps, %d updates: return %.1f +- %.1f (length %.0f, %.1fs)",
                 self.env_steps, self.updates, mean, std, length, time.monotonic() - t0)

    def start(self) -> None:
        """Publish the first weights and, on a fresh start, evaluate the untrained policy (every curve's baseline)."""
        self.publish_weights()
        if not self.resumed:
            self.evaluate()
            self.next_eval = self.cfg.eval_interval

    # -- training ------------------------------------------------------------------
    def see(self, meta: dict[str, Any]) -> None:
        """Take in a reply's description of the buffer (any reply: a not-ready one too)."""
        self.env_steps = max(self.env_steps, int(meta.get("env_steps", 0)))
        if "expert_transitions" in meta:
            self.buffer_meta = meta

    def step(self, batch: P.BatchReply) -> None:
        """Train on one `ok` reply (`meta["batches"]` updates) and publish weights and checkpoint when due."""
        self.see(batch.meta)
        n, size = int(batch.meta["batches"]), int(batch.meta["batch_size"])
        versions = batch.arrays["policy_version"].reshape(n, size)
        online = int(batch.meta.get("online_rows", size))  # rows of each batch from D_O; the rest are D_E's
        if self.gasil is not None and online < size:
            raise BufferMismatch("--algo gasil: the buffer service mixes D_E rows with constant rewards into the batches; "
                                 "it runs --algo silcr or sqil (start it with --algo gasil)")
        lag = _mean_lag(self.policy_version, versions[:, :online])
        if lag is not None:
            self.policy_lag.append(lag)
        if online < size and (age := _mean_lag(self.policy_version, versions[:, online:])) is not None:
            self.expert_age.append(age)
        t0 = time.monotonic()
        self.train_on(batch.arrays, n, size)
        self.update_time += time.monotonic() - t0
        if self.updates // self.cfg.weights_interval != (self.updates - n) // self.cfg.weights_interval:
            self.policy_version += 1
            self.publish_weights()
        if self.updates >= self.next_checkpoint:
            self.checkpoint()
            self.next_checkpoint = (self.updates // self.cfg.checkpoint_interval + 1) * self.cfg.checkpoint_interval

    def sample_request(self) -> P.SampleRequest:
        """What this learner asks the buffer for: GASIL also wants its discriminator's rows."""
        cfg = self.cfg
        if self.gasil is None:
            return P.SampleRequest(cfg.batches_per_request, cfg.batch_size)
        return P.SampleRequest(cfg.batches_per_request, cfg.batch_size, cfg.disc_batch_size, cfg.recent_window)

    def train_on(self, arrays: dict[str, np.ndarray], batches: int, batch_size: int) -> None:
        if self.gasil is not None and "disc_expert_obs" not in arrays:
            raise BufferMismatch("--algo gasil: the buffer service sent no discriminator rows; it runs another --algo "
                                 "or predates GASIL (start it with --algo gasil)")
        t = batch_tensors(arrays, self.device)
        term = t["terminated"].float()
        trunc = t["truncated"].float()
        for b in range(batches):
            s = slice(b * batch_size, (b + 1) * batch_size)
            rewards = t["rewards"][s]
            if self.gasil is not None:
                if self.updates % self.cfg.disc_interval == 0:
                    m = self.cfg.disc_batch_size
                    d = slice(b * m, (b + 1) * m)
                    self._disc_stats = self.gasil.update(t["disc_expert_obs"][d], t["disc_expert_actions"][d],
                                                         t["disc_recent_obs"][d], t["disc_recent_actions"][d])
                # r_D from the discriminator as it is now, for this batch only (never stored)
                rewards, r_d_mean = self.gasil.shape(rewards, t["obs"][s], t["actions"][s])
            self._last_stats = self.sac.update(t["obs"][s], t["actions"][s], rewards, t["next_obs"][s], term[s], trunc[s])
            if self.gasil is not None:
                self._last_stats |= self._disc_stats | {"gasil_reward_mean": r_d_mean}
            self.updates += 1

    def poll(self) -> None:
        """Evaluate when the environment-step schedule says so."""
        if self.env_steps >= self.next_eval:
            self.evaluate()
            self.next_eval = (self.env_steps // self.cfg.eval_interval + 1) * self.cfg.eval_interval

    def target_updates(self) -> int:
        return int(max(0, self.cfg.total_steps - self.cfg.learning_starts) * self.cfg.samples_per_insert)

    def done(self, starved: bool) -> bool:
        """The budget is spent: every step collected and trained on, or nothing more to be had (`starved`)."""
        return self.env_steps >= self.cfg.total_steps and (self.updates >= self.target_updates() or starved)

    def finish(self, finished: bool) -> None:
        """Last weights and evaluation if the run finished, a checkpoint either way, then close the records."""
        if finished:
            self.policy_version += 1
            self.publish_weights()
            if self.updates != self.last_eval_updates:  # not the policy the schedule just evaluated
                self.evaluate()
            log.info("finished: %d env steps, %d updates, last eval return %s", self.env_steps, self.updates,
                     self.last_eval_return)
        self.checkpoint()
        self.progress.close()

    # -- reporting -------------------------------------------------------------------
    @property
    def last_losses(self) -> dict[str, float]:
        """The last update's statistics and the divergence count; reading them waits for the device, so only when reporting."""
        out: dict[str, float] = as_floats(self._last_stats)
        out["q_bound_exceeded"] = int(self.sac.q_bound_exceeded)
        return out

    def stats(self) -> dict[str, Any]:
        """The learner's stats message (the batch stream adds its own counters)."""
        elapsed = time.monotonic() - self.started
        losses = self.last_losses
        return {
            "time": time.time(),
            "updates": self.updates,
            "policy_version": self.policy_version,
            "env_steps": self.env_steps,
            "total_steps": self.cfg.total_steps,
            "last_eval_return": self.last_eval_return,
            "updates_per_s": self.updates / max(elapsed, 1e-9),
            "duty_cycle": self.update_time / max(elapsed, 1e-9),
            "policy_lag_mean": float(np.mean(self.policy_lag)) if self.policy_lag else None,
            "expert_age_mean": float(np.mean(self.expert_age)) if self.expert_age else None,
            "device": str(self.device),
        } | {k: P.finite_or_none(v) for k, v in losses.items()} | {"q_bound_exceeded": losses["q_bound_exceeded"]}

    def record_scalars(self, stats: dict[str, Any]) -> None:
        """The training statistics as TensorBoard scalars at the current env step."""
        if self.updates:
            keys = [*self._last_stats, "q_bound_exceeded", "updates_per_s"]
            self.progress.scalars({f"train/{k}": stats[k] for k in keys if stats.get(k) is not None}, self.env_steps)


def run_learner(cfg: Config, stop: StopFlag) -> int:
    spec = EnvSpec.of(cfg.env)
    keys = P.Keys(cfg.run)
    conf = session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)
    with open_session(conf) as session:
        stop_on_shutdown(session, keys, stop)
        stats_pub = StatsPublisher(session, keys.stats_learner)
        shutdown = Shutdown(session, keys)
        token = session.liveliness().declare_token(keys.alive("learner"))
        lrn = Learner(cfg, spec, ZenohWeightsServer(session, keys))
        log.info("learner for run %s on %s: %s, networks %s, batch %d, %d env steps",
                 cfg.run, lrn.device, cfg.algo, cfg.hidden, cfg.batch_size, cfg.total_steps)
        stream = ZenohBatchStream(session, keys, lrn.sample_request(), cfg.requests_in_flight, stop)
        lrn.start()
        stream.wait_for_buffer()
        finished = False
        mismatch: BufferMismatch | None = None
        next_stats = time.monotonic()
        for batch in stream:
            if batch is not None:
                try:
                    lrn.step(batch)
                except BufferMismatch as e:
                    log.error("%s", e)
                    mismatch = e
                    break
            else:
                lrn.see(stream.last_meta)
            lrn.poll()
            if time.monotonic() >= next_stats:
                stats = lrn.stats() | stream.stats()
                stats_pub.put(stats)
                lrn.record_scalars(stats)
                next_stats = time.monotonic() + cfg.stats_interval
            if lrn.done(starved=stream.rate_limited):
                finished = True
                break
        lrn.finish(finished)
        stats_pub.put({"time": time.time(), "updates": lrn.updates, "policy_version": lrn.policy_version,
                       "env_steps": lrn.env_steps, "last_eval_return": lrn.last_eval_return, "finished": finished})
        if finished:
            shutdown.announce("finished")
        else:
            log.info("stopping (%s) at %d updates", stop.reason, lrn.updates)
        token.undeclare()
    return 1 if mismatch else 0
